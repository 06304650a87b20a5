"""The committed sample bags (``bags/``) and how to re-create one that is missing.

Each sample bag is a simulator scenario written with a fixed seed (``make bags``); when a
checkout lacks one, :func:`ensure_bag` simulates it into a fallback folder.
"""

from __future__ import annotations

from pathlib import Path

#: seeds of ``make bags`` (bags/README.md), used when a sample bag has to be simulated
SAMPLE_SEEDS = {"step20-ccw": 1, "step30-cw": 2, "sine": 3, "surface-change": 4}


def ensure_bag(name: str, bags: Path, fallback: Path) -> Path:
    """``bags/<name>`` if it exists, else simulate it (``make bags``' seed) into ``fallback/<name>``."""
    path = bags / name
    if (path / "metadata.yaml").is_file():
        return path
    target = fallback / name
    if (target / "metadata.yaml").is_file():
        return target
    from transplanter_ident.bags import SimBagOptions, write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    print(f"demo: {path} not found; simulating scenario {name} (seed {SAMPLE_SEEDS[name]}) into {target}")
    fallback.mkdir(parents=True, exist_ok=True)
    write_sim_bag(simulate(build_config(name, seed=SAMPLE_SEEDS[name])), target, SimBagOptions(overwrite=True))
    return target
