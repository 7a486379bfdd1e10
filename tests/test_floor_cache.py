"""The finite-N floors stored by content (harness/observers/floor_cache.py): reused bit-identical,
missed on any change of input, never trusted when damaged, whole under concurrent
writers, and off when disabled. Small floors (N = 64, 2 draws, 12 x 12 grid): ~10 ms each.
"""

import json
import multiprocessing
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

import harness.observers.swarm_metrics
from analysis.load import load_run
from harness.api import CONFIG_DIR
from harness.grid import Grid
from harness.observers.floor_cache import (
    FloorCache,
    FloorCacheWarning,
    canonical,
    describe_density,
    digest,
    floor_key,
)
from harness.observers.swarm import SwarmTruth
from harness.runs.identity import config_hash
from harness.runs.run import run
from harness.targets.densities import DEFAULT_TARGET, GaussianMixture, Target, Uniform

BASE = {"grid_n": 12, "n_robots": 64, "bandwidth": 0.08, "draws": 2, "seed": 3}
FLOOR_KEYS = {
    f"swarm_{m}_floor_{k}" for m in ("l2", "w2") for k in ("mean", "lo", "hi", "draws")
} | {"swarm_w2_method"}


def truth(cache, density=DEFAULT_TARGET, **change) -> tuple[SwarmTruth, int]:
    """The swarm observer of BASE with ``change``, and its robots' count."""
    p = {**BASE, **change}
    grid = Grid.square(p["grid_n"])
    target = Target.from_density(grid, density)
    observer = SwarmTruth(
        grid,
        target,
        1,
        p["bandwidth"],
        True,
        "auto",
        1,
        1,
        floor_draws=p["draws"],
        seed=p["seed"],
        floor_cache=None if cache is None else str(cache),
    )
    return observer, p["n_robots"]


def record(cache, density=DEFAULT_TARGET, **change) -> dict[str, str]:
    observer, n = truth(cache, density, **change)
    return observer.floor_record(n)


@pytest.fixture
def calls(monkeypatch) -> list[int]:
    """Counts the calls of harness.observers.swarm_metrics.floors (the computation)."""
    seen: list[int] = []
    compute = harness.observers.swarm_metrics.floors

    def counted(*args, **kwargs):
        seen.append(1)
        return compute(*args, **kwargs)

    monkeypatch.setattr(harness.observers.swarm_metrics, "floors", counted)
    return seen


def refuse_to_compute(*args, **kwargs):
    raise AssertionError("the floors were computed, not read from the cache")


def without_source(theory: dict[str, str]) -> list[tuple[str, str]]:
    return [(k, v) for k, v in theory.items() if k != "swarm_floor_source"]


def test_a_second_run_reads_the_cache_bit_identical_without_computing(tmp_path, calls, monkeypatch):
    first = record(tmp_path)
    assert len(calls) == 1 and first["swarm_floor_source"] == "computed"
    assert FLOOR_KEYS <= set(first)
    (path,) = tmp_path.glob("*.json")
    assert path.stem == first["swarm_floor_key"]
    monkeypatch.setattr(harness.observers.swarm_metrics, "floors", refuse_to_compute)
    with warnings.catch_warnings():
        warnings.simplefilter("error", FloorCacheWarning)
        second = record(tmp_path)
    assert second["swarm_floor_source"] == "cache"
    # the same strings in the same order: the theory record is byte-identical but for the source
    assert without_source(second) == without_source(first)
    # each float is its shortest round-trip repr, so it parses back to the same bits
    numbers = [k for k in FLOOR_KEYS if k.endswith(("_mean", "_lo", "_hi"))]
    assert all(repr(float(second[k])) == second[k] == first[k] for k in numbers)


@pytest.mark.parametrize(
    "change",
    [
        {"n_robots": 65},
        {"bandwidth": 0.09},
        {"draws": 3},
        {"seed": 4},
        {"grid_n": 13},
        {"density": Uniform()},
        {"density": GaussianMixture(((0.3, 0.3),), (0.1,), (1.0,), floor=0.3)},
    ],
    ids=["N", "bandwidth", "draws", "seed", "grid", "target", "target-params"],
)
def test_a_change_of_any_input_misses(tmp_path, calls, change):
    base = record(tmp_path)
    changed = record(tmp_path, **change)
    assert len(calls) == 2, "the changed floors must be computed"
    assert changed["swarm_floor_source"] == "computed"
    assert changed["swarm_floor_key"] != base["swarm_floor_key"]
    assert len(list(tmp_path.glob("*.json"))) == 2
    assert record(tmp_path)["swarm_floor_source"] == "cache"  # the base is still there


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _edit_value(path: Path) -> None:
    data = json.loads(path.read_text())
    data["floors"]["swarm_l2_floor_mean"] = "0.001"  # the checksum is now stale
    path.write_text(json.dumps(data))


def _other_inputs(path: Path) -> None:
    data = json.loads(path.read_text())
    data["inputs"]["n_robots"] = 65  # another floor's file under this key
    path.write_text(json.dumps(data))


def _other_key(path: Path) -> None:
    data = json.loads(path.read_text())
    data["key"] = "0" * 64
    path.write_text(json.dumps(data))


def _not_json(path: Path) -> None:
    path.write_bytes(b"\x00\xff garbage")


def _number_floor(path: Path) -> None:
    data = json.loads(path.read_text())
    data["floors"]["swarm_l2_floor_mean"] = 0.001
    data["checksum"] = digest(canonical(data["floors"]))
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(
    "damage",
    [_truncate, _edit_value, _other_inputs, _other_key, _not_json, _number_floor],
    ids=["truncated", "stale-checksum", "other-inputs", "other-key", "not-json", "not-strings"],
)
def test_a_damaged_file_is_recomputed_and_rewritten_never_trusted(tmp_path, calls, damage):
    good = record(tmp_path)
    (path,) = tmp_path.glob("*.json")
    damage(path)
    with pytest.warns(FloorCacheWarning, match="ignoring"):
        again = record(tmp_path)
    assert len(calls) == 2 and again["swarm_floor_source"] == "computed"
    assert without_source(again) == without_source(good)
    # rewritten whole: the next run reads it
    assert record(tmp_path)["swarm_floor_source"] == "cache" and len(calls) == 2


def test_concurrent_threads_writing_one_key_leave_a_whole_file(tmp_path):
    observer, n = truth(tmp_path)
    inputs = observer.floor_inputs(n)
    floors = {k: v for k, v in record(None).items() if k in FLOOR_KEYS}
    cache = FloorCache(tmp_path)
    barrier = threading.Barrier(16)
    seen, errors = [], []

    def writer():
        try:
            barrier.wait()
            for _ in range(20):
                assert cache.put(inputs, floors) is not None
                seen.append(cache.get(inputs))
        except BaseException as err:  # reported below
            errors.append(err)

    with warnings.catch_warnings():
        warnings.simplefilter("error", FloorCacheWarning)
        threads = [threading.Thread(target=writer) for _ in range(16)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert not errors, errors
    assert seen and all(s == floors for s in seen)
    assert [p.name for p in tmp_path.iterdir()] == [f"{floor_key(inputs)}.json"]


def _floor_in_process(cache: str, barrier, out) -> None:
    barrier.wait()
    with warnings.catch_warnings():
        warnings.simplefilter("error", FloorCacheWarning)
        out.put(record(cache))


def test_concurrent_processes_computing_one_floor_all_succeed(tmp_path):
    ctx = multiprocessing.get_context("fork")
    barrier, out = ctx.Barrier(4), ctx.Queue()
    procs = [ctx.Process(target=_floor_in_process, args=(tmp_path, barrier, out)) for _ in range(4)]
    for p in procs:
        p.start()
    results = [out.get(timeout=60) for _ in procs]
    for p in procs:
        p.join(timeout=60)
    assert [p.exitcode for p in procs] == [0] * 4
    assert len({tuple(without_source(r)) for r in results}) == 1
    (path,) = tmp_path.iterdir()
    assert FloorCache(tmp_path).get(truth(tmp_path)[0].floor_inputs(64)) is not None
    assert path.stem == results[0]["swarm_floor_key"]


@pytest.mark.parametrize("disabled", [None, ""])
def test_a_disabled_cache_computes_every_time(tmp_path, calls, monkeypatch, disabled):
    monkeypatch.chdir(tmp_path)  # a relative path '' must not become the working directory
    first, second = record(disabled), record(disabled)
    assert len(calls) == 2
    assert first["swarm_floor_source"] == second["swarm_floor_source"] == "computed"
    assert first == second and first["swarm_floor_key"]
    assert not list(tmp_path.iterdir())


def test_an_unwritable_cache_warns_and_the_floors_are_computed(tmp_path, calls):
    blocked = tmp_path / "file"
    blocked.write_text("not a directory")
    with pytest.warns(FloorCacheWarning, match="cannot write"):
        first = record(blocked / "floors")
    assert first["swarm_floor_source"] == "computed" and len(calls) == 1


@dataclass(frozen=True)
class Shifted(GaussianMixture):
    """A subclass: it may sample differently, so it has no content description."""


def test_a_target_without_a_faithful_description_is_never_cached(tmp_path, calls):
    density = Shifted(((0.5, 0.5),), (0.1,), (1.0,))
    assert describe_density(density) is None
    assert describe_density(DEFAULT_TARGET) is not None
    first, second = record(tmp_path, density), record(tmp_path, density)
    assert len(calls) == 2 and "swarm_floor_key" not in first
    assert first["swarm_floor_source"] == second["swarm_floor_source"] == "computed"
    assert not list(tmp_path.iterdir())


def test_runs_reuse_floors_and_the_cache_does_not_change_the_identity(
    tmp_path, compose, smoke, monkeypatch
):
    cache = tmp_path / "floors"
    cfg = compose([*smoke, f"log.floor_cache={cache}"])
    assert config_hash(cfg) == config_hash(compose([*smoke, "log.floor_cache=null"]))
    assert config_hash(cfg) == config_hash(compose(smoke))
    run(cfg, tmp_path / "a")
    monkeypatch.setattr(harness.observers.swarm_metrics, "floors", refuse_to_compute)
    run(compose([*smoke, f"log.floor_cache={cache}"]), tmp_path / "b")
    a, b = load_run(tmp_path / "a"), load_run(tmp_path / "b")
    ta, tb = a.metadata["theory"], b.metadata["theory"]
    assert (ta["swarm_floor_source"], tb["swarm_floor_source"]) == ("computed", "cache")
    assert without_source(ta) == without_source(tb)
    assert (cache / f"{ta['swarm_floor_key']}.json").is_file()
    # the sweep's job directories are not named by the cache's location
    closed_loop = yaml.safe_load((CONFIG_DIR / "closed_loop.yaml").read_text())
    assert (
        "log.floor_cache"
        in closed_loop["hydra"]["job"]["config"]["override_dirname"]["exclude_keys"]
    )


def test_a_floor_cache_that_is_not_a_path_is_refused(refusal):
    message = refusal(["log.floor_cache=5"])
    assert message is not None and message.startswith("invalid config: log.floor_cache="), message
