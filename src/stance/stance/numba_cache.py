"""numba's on-disk cache, keyed on the whole library's source.

numba checks a cached function against its own file only, not against the files of the
compiled functions it calls (numba #8396): after an edit to hierarchy.py, pik's compiled
clamping loop would go on running the old hierarchy kernels from the cache, silently.
The library's cache therefore lives in a directory named after a hash of all its Python
sources (under $NUMBA_CACHE_DIR if set, else the package's __pycache__): any edit gives a
fresh directory, and the directories of other sources are removed.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import numba

PACKAGE = Path(__file__).resolve().parent
PREFIX = "numba-"


def source_digest(package: Path = PACKAGE) -> str:
    """Hash of every .py file of the package (paths and contents), 16 hex digits."""
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(str(path.relative_to(package)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def use_source_keyed_cache() -> Path:
    """Point numba's cache at this source's directory (before any cached function is
    defined) and remove the directories of other sources; returns the directory."""
    base = Path(os.environ.get("NUMBA_CACHE_DIR") or PACKAGE / "__pycache__")
    directory = base / f"{PREFIX}{source_digest()}"
    numba.config.CACHE_DIR = str(directory)
    if base.is_dir():
        for other in base.glob(f"{PREFIX}*"):
            if other != directory:
                shutil.rmtree(other, ignore_errors=True)  # another process may hold it
    return directory
