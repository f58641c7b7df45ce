"""Demonstration datasets: the on-disk format (:mod:`.format`), its checks (:mod:`.checks`) and the segment
sampler of training (:mod:`.sampler`). The format knows no simulator: suites (``tar_rl.collectors``) and
importers (``tar_rl.importers``) write datasets in it."""

from .checks import (
    DIGEST_FILE,
    DTYPES,
    METADATA_FILE,
    DatasetError,
    check_content,
    content_digest,
    positive_int,
)
from .format import (
    BUFFER_DIR,
    FORMAT_VERSION,
    DemoDataset,
    array_stats,
    cache_key,
    clean_temp_siblings,
    load_dataset,
    package_version,
    seal_dataset,
    steps_tensordict,
    write_dataset,
)
from .sampler import EPISODE_LENGTH_KEY, VALID_KEY, SegmentSampler

__all__ = [
    "BUFFER_DIR",
    "DIGEST_FILE",
    "DTYPES",
    "EPISODE_LENGTH_KEY",
    "FORMAT_VERSION",
    "METADATA_FILE",
    "VALID_KEY",
    "DatasetError",
    "DemoDataset",
    "SegmentSampler",
    "array_stats",
    "cache_key",
    "check_content",
    "clean_temp_siblings",
    "content_digest",
    "load_dataset",
    "package_version",
    "positive_int",
    "seal_dataset",
    "steps_tensordict",
    "write_dataset",
]
