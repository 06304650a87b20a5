"""transplanter_ident: online IPSO-EKF identification of a rice transplanter's cornering stiffness."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__version__ = "0.1.0"



def _numba_cache_dir() -> Path:
    """A numba cache folder keyed by the compiled sources.

    numba invalidates a cached function only when its own file changes, but the kernels inline
    code of other modules (and take their options from jit.py): keying the folder by every
    source of the package keeps the cache honest.
    """
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(here.rglob("*.py")):
        digest.update(str(path.relative_to(here)).encode())
        digest.update(path.read_bytes())
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return root / "transplanter_ident" / f"numba-{digest.hexdigest()[:16]}"


if "NUMBA_CACHE_DIR" not in os.environ:
    import numba

    numba.config.CACHE_DIR = str(_numba_cache_dir())
