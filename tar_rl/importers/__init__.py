"""Importers of demonstrations stored in other formats into tar-rl's dataset format (:mod:`tar_rl.data`).

* :func:`import_robomimic`: robomimic / LIBERO HDF5 files (low-dimensional observations).
* :func:`import_lerobot`: LeRobot datasets on local disk (v3.x / v2.x folders, or TorchRL's converted copy).
* :func:`dataset_info` / :func:`format_info`: what ``tar-rl data info PATH`` prints, for any dataset folder.
"""

from tar_rl.importers.common import IMPORTERS, DemoImportError, Importer
from tar_rl.importers.info import dataset_info, format_info
from tar_rl.importers.lerobot import import_lerobot
from tar_rl.importers.robomimic import import_robomimic

__all__ = [
    "IMPORTERS",
    "DemoImportError",
    "Importer",
    "dataset_info",
    "format_info",
    "import_lerobot",
    "import_robomimic",
]
