"""Importers of demonstrations stored in other formats into tar-rl's dataset format (:mod:`tar_rl.data`).

* :func:`import_robomimic`: robomimic / LIBERO HDF5 files (low-dimensional observations).
* :func:`dataset_info` / :func:`format_info`: what ``tar-rl data info PATH`` prints, for any dataset folder.
"""

from tar_rl.importers.info import dataset_info, format_info
from tar_rl.importers.robomimic import DemoImportError, import_robomimic

__all__ = ["DemoImportError", "dataset_info", "format_info", "import_robomimic"]
