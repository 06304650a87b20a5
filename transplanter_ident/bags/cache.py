"""Decode each bag once: a cache of its epochs (the filter's input, paper eq. 7) and ground truth.

Tuning reads the same bags again and again with the same parameters; decoding MCAP is the slow
part of a short run. :func:`load_bag_epochs` keeps what :func:`.reader.read_bag` produced in an
``.npz`` file under ``$XDG_CACHE_HOME/transplanter_ident/epochs`` (default
``~/.cache/transplanter_ident/epochs``), keyed by

* the bag's identity: its resolved path and the name, size and modification time (ns) of
  every file in it (``metadata.yaml``, the ``.mcap`` files), so a re-recorded bag misses;
* every parameter that is not ``ekf.*`` (frames, antenna, topics and their types, the
  steering joint, ``max_steering``, and any key added later: the filter's own ``ekf.*``
  settings do not shape the epochs, everything else might), and ``ekf.measurement``, which does
  (:data:`EPOCH_SHAPING_EKF_KEYS`: a single antenna's course makes each velocity its own epoch);
* a digest of the code that decodes and assembles epochs (``epochs/`` and ``bags/``) and a
  format version, so a change there re-decodes.

The file is written atomically (temp file, then rename). A file that cannot be read, or whose
stored key or arrays do not match, is ignored and rebuilt; a cache directory that cannot be
written costs the cache, not the run (the reason is returned as a note).
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from transplanter_ident.bags.reader import Truth, read_bag
from transplanter_ident.config.params_file import EstimatorParams, params_to_flat
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.files import atomic_output_file, one_line

FORMAT = 1
_TRUTH_FIELDS = ("t", "cf", "cr", "vx", "vy", "r")
_EPOCH_COLUMNS = len(Epoch.__dataclass_fields__)


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/transplanter_ident/epochs`` (``~/.cache`` when unset)."""
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return root / "transplanter_ident" / "epochs"


def _code_digest() -> str:
    here = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for package in ("epochs", "bags"):
        for path in sorted((here / package).glob("*.py")):
            digest.update(path.name.encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def bag_identity(bag: str | Path) -> dict[str, Any]:
    """Resolved path and (name, size, mtime_ns) of each file of the bag."""
    path = Path(bag).resolve()
    files = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
    stats = []
    for file in files:
        st = file.stat()
        stats.append([file.name, st.st_size, st.st_mtime_ns])
    return {"path": str(path), "files": stats}


#: the filter's parameters that shape its epochs too (epochs.settings.AssemblerSettings.from_params reads them)
EPOCH_SHAPING_EKF_KEYS = ("ekf.measurement",)


def cache_key(bag: str | Path, params: EstimatorParams) -> str:
    """The JSON text the cache file is keyed by (bag identity, the parameters that shape epochs, code, format)."""
    shaping = {k: v for k, v in sorted(params_to_flat(params).items())
               if not k.startswith("ekf.") or k in EPOCH_SHAPING_EKF_KEYS}
    material = {"format": FORMAT, "code": _code_digest(), "bag": bag_identity(bag), "params": shaping}
    return json.dumps(material, sort_keys=True, default=repr)


def cache_path(bag: str | Path, key: str, cache_dir: Path) -> Path:
    """``<cache_dir>/<bag name>-<sha256 of the key, 20 hex>.npz``."""
    name = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(bag).resolve().name) or "bag"
    return cache_dir / f"{name}-{hashlib.sha256(key.encode()).hexdigest()[:20]}.npz"


@dataclass(frozen=True)
class DecodedBag:
    """A bag's epoch columns (``Epoch`` field order), its ground truth, and where they came from."""

    bag: str
    columns: np.ndarray  # (N, 8)
    truth: Truth | None
    source: str  # "cache" or "bag"
    note: str = ""  # why the cache was not used or not written (empty if it was)

    @property
    def epochs(self) -> EpochArrays:
        """The epochs as :class:`EpochArrays` (the values are bit-identical to the decoded ones)."""
        return EpochArrays([Epoch(*map(float, row)) for row in self.columns])


def _columns(epochs: EpochArrays) -> np.ndarray:
    return epochs.rows()


def _read(path: Path, key: str) -> tuple[np.ndarray, Truth | None] | None:
    """The cached arrays, or None if the file is missing, unreadable or for another key."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None
            columns = np.array(data["epochs"], dtype=np.float64)
            truth = None
            if bool(data["has_truth"]):
                truth = Truth(**{f: np.array(data[f"truth_{f}"], dtype=np.float64) for f in _TRUTH_FIELDS})
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    if columns.ndim != 2 or columns.shape[1] != _EPOCH_COLUMNS or len(columns) == 0:
        return None
    if truth is not None and len({len(getattr(truth, f)) for f in _TRUTH_FIELDS}) != 1:
        return None
    return columns, truth


def _write(path: Path, key: str, columns: np.ndarray, truth: Truth | None) -> str:
    """Store the arrays atomically; returns "" or the reason it could not."""
    arrays: dict[str, Any] = {"key": np.array(key), "epochs": columns, "has_truth": np.array(truth is not None)}
    if truth is not None:
        arrays.update({f"truth_{f}": np.asarray(getattr(truth, f), dtype=np.float64) for f in _TRUTH_FIELDS})
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output_file(path, "wb", encoding=None) as handle:
            np.savez(handle, **arrays)
    except (OSError, ValueError) as exc:
        return f"epoch cache not written ({one_line(exc)})"
    return ""


def cached_bag_epochs(bag: str, params: EstimatorParams, cache_dir: str | Path) -> DecodedBag | None:
    """The bag's epochs if the cache holds them (valid and for this key), else None; never decodes."""
    try:
        key = cache_key(bag, params)
    except OSError:
        return None
    cached = _read(cache_path(bag, key, Path(cache_dir)), key)
    return DecodedBag(bag, cached[0], cached[1], "cache") if cached is not None else None


def load_bag_epochs(bag: str, params: EstimatorParams, cache_dir: str | Path | None = None,
                    allow_partial: bool = False) -> DecodedBag:
    """The bag's epochs and ground truth: from the cache if it holds them, else decoded and cached.

    ``cache_dir`` None disables the cache (always decode). Bag errors are :class:`.errors.BagError`;
    a bag with fewer readable messages than its metadata counts is one unless ``allow_partial``.
    """
    if cache_dir is None:
        data = read_bag(bag, params, truth=True, allow_partial=allow_partial)
        return DecodedBag(bag, _columns(data.epochs), data.truth, "bag")
    try:
        key = cache_key(bag, params)
    except OSError:  # no such bag, or unreadable: read_bag says why
        data = read_bag(bag, params, truth=True, allow_partial=allow_partial)
        return DecodedBag(bag, _columns(data.epochs), data.truth, "bag")
    path = cache_path(bag, key, Path(cache_dir))
    cached = _read(path, key)
    if cached is not None:
        return DecodedBag(bag, cached[0], cached[1], "cache")
    data = read_bag(bag, params, truth=True, allow_partial=allow_partial)
    columns = _columns(data.epochs)
    return DecodedBag(bag, columns, data.truth, "bag", _write(path, key, columns, data.truth))


def store_bag_epochs(bag: str, params: EstimatorParams, epochs: EpochArrays, truth: Truth | None,
                     cache_dir: str | Path | None = None) -> DecodedBag:
    """A :class:`DecodedBag` of epochs assembled elsewhere (``tuner --estimate-delay``), cached under ``params``.

    So a later run with the same parameters (the estimated ``gnss.delay`` among them) skips decoding.
    """
    columns = _columns(epochs)
    if cache_dir is None:
        return DecodedBag(bag, columns, truth, "bag")
    try:
        key = cache_key(bag, params)
    except OSError as exc:
        return DecodedBag(bag, columns, truth, "bag", f"epoch cache not written ({one_line(exc)})")
    return DecodedBag(bag, columns, truth, "bag", _write(cache_path(bag, key, Path(cache_dir)), key, columns, truth))
