"""Tests of the epoch cache (decode each bag once; the epochs of paper eq. 7 and the ground truth)."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import transplanter_ident.bags.cache as cache
import transplanter_ident.cli.tuner as tuner
from transplanter_ident.bags import BagError, read_bag
from transplanter_ident.config.params_file import EstimatorParams, FrameConfig, flat_to_params
from transplanter_ident.ekf.joint_ekf import kernel_input


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory) -> Path:  # noqa: ANN001
    """A 20 s simulated bag (100 epochs) with ground truth."""
    from transplanter_ident.bags import write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    path = tmp_path_factory.mktemp("cache_bag") / "sine20"
    write_sim_bag(simulate(build_config("sine", duration=20.0, seed=21)), path)
    return path


class CountingReader:
    """Stands in for ``read_bag`` in the cache module and counts the calls."""

    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN204
        self.calls += 1
        return read_bag(*args, **kwargs)


@pytest.fixture
def reader(monkeypatch) -> CountingReader:  # noqa: ANN001
    counting = CountingReader()
    monkeypatch.setattr(cache, "read_bag", counting)
    return counting


def test_second_load_skips_decoding_and_gives_identical_epochs(sim_bag, tmp_path, reader) -> None:  # noqa: ANN001
    params = EstimatorParams()
    first = cache.load_bag_epochs(str(sim_bag), params, tmp_path)
    assert (first.source, reader.calls, first.note) == ("bag", 1, "")
    assert len(list(tmp_path.glob("*.npz"))) == 1 and not list(tmp_path.glob(".*"))  # no temp file left
    second = cache.load_bag_epochs(str(sim_bag), params, tmp_path)
    assert (second.source, reader.calls) == ("cache", 1)
    np.testing.assert_array_equal(second.columns, first.columns)
    direct = read_bag(sim_bag, params, truth=True)
    np.testing.assert_array_equal(kernel_input(second.epochs), kernel_input(direct.epochs))
    np.testing.assert_array_equal(second.epochs.longitudinal_velocity, direct.epochs.longitudinal_velocity)
    for name in ("t", "cf", "cr", "vx", "vy", "r"):
        np.testing.assert_array_equal(getattr(second.truth, name), getattr(direct.truth, name))


def test_key_covers_every_non_ekf_parameter_and_the_measurement_and_ignores_other_ekf(sim_bag) -> None:  # noqa: ANN001
    base = EstimatorParams()
    key = cache.cache_key(sim_bag, base)
    ekf_only = flat_to_params({"ekf.process_noise": [1e-3, 1e-3, 1e-5, 1e-5], "ekf.min_speed": 0.5})
    assert cache.cache_key(sim_bag, ekf_only) == key
    changed = [
        replace(base, frames=FrameConfig(velocity="ned")),
        flat_to_params({"vehicle.antenna_x": 0.4}),
        flat_to_params({"vehicle.max_steering": 0.5}),
        flat_to_params({"topics.heading": "/other/heading"}),
        flat_to_params({"steering.joint_name": "wheel"}),
        flat_to_params({"topics.velocity_type": "geometry_msgs/msg/TwistWithCovarianceStamped"}),
        flat_to_params({"gnss.delay": 0.04}),
        flat_to_params({"ekf.measurement": "course"}),  # a single antenna: each velocity its own epoch
    ]
    keys = {cache.cache_key(sim_bag, p) for p in changed}
    assert key not in keys and len(keys) == len(changed)


def test_a_course_is_not_served_the_epochs_of_a_heading(sim_bag, tmp_path, reader) -> None:  # noqa: ANN001
    """The same bag tuned with a heading, then with one antenna (ekf.measurement course): decoded again.

    Before session 30 the key left every ekf.* out, and the course run got the heading's epochs (a measured vy).
    """
    heading = cache.load_bag_epochs(str(sim_bag), EstimatorParams(), tmp_path)
    course_params = flat_to_params({"ekf.measurement": "course"})
    course = cache.load_bag_epochs(str(sim_bag), course_params, tmp_path)
    assert (heading.source, course.source, reader.calls) == ("bag", "bag", 2)
    assert np.all(np.isfinite(heading.epochs.lateral_velocity))
    assert np.all(np.isnan(course.epochs.lateral_velocity))  # one antenna measures no vy
    direct = read_bag(sim_bag, course_params, truth=True)
    np.testing.assert_array_equal(kernel_input(course.epochs), kernel_input(direct.epochs))


def test_a_changed_bag_is_decoded_again(sim_bag, tmp_path, reader) -> None:  # noqa: ANN001
    params = EstimatorParams()
    cache.load_bag_epochs(str(sim_bag), params, tmp_path)
    mcap = next(sim_bag.glob("*.mcap"))
    stat = mcap.stat()
    os.utime(mcap, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    try:
        again = cache.load_bag_epochs(str(sim_bag), params, tmp_path)
    finally:
        os.utime(mcap, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert again.source == "bag" and reader.calls == 2


@pytest.mark.parametrize("damage", ["garbage", "truncated", "other_key", "bad_shape"])
def test_a_corrupt_cache_file_is_ignored_and_rebuilt(damage: str, sim_bag, tmp_path, reader) -> None:  # noqa: ANN001
    params = EstimatorParams()
    first = cache.load_bag_epochs(str(sim_bag), params, tmp_path)
    (path,) = tmp_path.glob("*.npz")
    if damage == "garbage":
        path.write_bytes(os.urandom(300))
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:200])
    else:
        with np.load(path) as data:
            arrays = dict(data)
        if damage == "other_key":
            arrays["key"] = np.array("something else")
        else:
            arrays["epochs"] = arrays["epochs"][:, :3]
        with open(path, "wb") as handle:
            np.savez(handle, **arrays)
    rebuilt = cache.load_bag_epochs(str(sim_bag), params, tmp_path)
    assert rebuilt.source == "bag" and reader.calls == 2
    np.testing.assert_array_equal(rebuilt.columns, first.columns)
    assert cache.load_bag_epochs(str(sim_bag), params, tmp_path).source == "cache"  # and stored again


def test_an_unwritable_cache_costs_the_cache_not_the_run(sim_bag, tmp_path) -> None:  # noqa: ANN001
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    decoded = cache.load_bag_epochs(str(sim_bag), EstimatorParams(), blocker / "epochs")
    assert decoded.source == "bag" and len(decoded.columns) > 50
    assert decoded.note.startswith("epoch cache not written")


def test_no_cache_and_bag_errors(sim_bag, tmp_path) -> None:  # noqa: ANN001
    decoded = cache.load_bag_epochs(str(sim_bag), EstimatorParams(), None)
    assert decoded.source == "bag"
    with pytest.raises(BagError, match="no such file"):
        cache.load_bag_epochs(str(tmp_path / "missing"), EstimatorParams(), tmp_path)
    assert not list(tmp_path.glob("*.npz"))


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path) -> None:  # noqa: ANN001
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache.default_cache_dir() == tmp_path / "transplanter_ident" / "epochs"


def test_tuner_says_where_the_epochs_came_from(sim_bag, tmp_path, capsys, reader) -> None:  # noqa: ANN001
    args = [str(sim_bag), "-o", str(tmp_path / "o.yaml"), "--particles", "3", "--iterations", "1", "--seed", "0",
            "--jobs", "1", "--epoch-cache", str(tmp_path / "epochs")]
    assert tuner.main(args) == 0
    first = capsys.readouterr()
    assert f"{sim_bag}: 100 epochs (decoded, cached in {tmp_path / 'epochs'})" in first.err
    yaml_first = (tmp_path / "o.yaml").read_bytes()
    assert tuner.main(args) == 0
    second = capsys.readouterr()
    assert f"{sim_bag}: 100 epochs (from the epoch cache)" in second.err and reader.calls == 1
    assert (tmp_path / "o.yaml").read_bytes() == yaml_first
