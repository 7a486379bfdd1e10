"""The floor cache trusts nothing it opens (harness/observers/floor_cache.py): a FIFO,
a device or a huge file in place of an entry, or a record whose floors are not numbers
the computation could give (even under a matching checksum), costs a warning and the
computation, never the run; what it rewrites replaces only a regular file.

Small floors (N = 64, 2 draws, 12 x 12 grid) as in tests/test_floor_cache.py.
"""

import contextlib
import json
import os
import subprocess
import sys
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

import harness.observers.swarm_metrics
from analysis.load import load_run
from harness.observers.floor_cache import FloorCache, FloorCacheWarning, canonical, digest
from harness.runs.run import run
from tests.test_floor_cache import record, truth, without_source

ROOT = Path(__file__).resolve().parents[1]


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


class Unblocker:
    """A watchdog for a FIFO: after ``after_s`` seconds it opens the FIFO's writing end
    (possible only while a reader waits in ``open()``) and closes it, so a reader
    blocked on it gets end-of-file instead of hanging the test. ``used`` says whether it
    had to.
    """

    def __init__(self, fifo: Path, after_s: float = 10.0) -> None:
        self.fifo, self.after_s = fifo, after_s
        self.done = threading.Event()
        self.used = False
        self.thread = threading.Thread(target=self._watch, daemon=True)

    def _watch(self) -> None:
        if self.done.wait(self.after_s):
            return
        while not self.done.is_set():
            try:
                fd = os.open(self.fifo, os.O_WRONLY | os.O_NONBLOCK)
            except OSError:  # no reader (yet)
                self.done.wait(0.05)
                continue
            self.used = True
            os.close(fd)
            self.done.wait(0.05)

    def __enter__(self) -> "Unblocker":
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.done.set()
        self.thread.join()


@contextlib.contextmanager
def cache_warnings() -> Iterator[list[str]]:
    """The messages of the :class:`FloorCacheWarning` raised inside (every one kept)."""
    messages: list[str] = []
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", FloorCacheWarning)
        yield messages
    messages.extend(str(w.message) for w in seen if issubclass(w.category, FloorCacheWarning))


def _fifo_in_place(path: Path) -> None:
    path.unlink()
    os.mkfifo(path)


def test_a_fifo_in_place_of_an_entry_is_never_opened_and_never_written_into(tmp_path, calls):
    good = record(tmp_path)
    (path,) = tmp_path.glob("*.json")
    _fifo_in_place(path)
    with Unblocker(path) as watchdog, cache_warnings() as seen:
        again = record(tmp_path)
    assert not watchdog.used, "reading the cache blocked on the FIFO"
    assert again["swarm_floor_source"] == "computed" and len(calls) == 2
    assert without_source(again) == without_source(good)
    assert [("a FIFO" in m, "not replacing" in m) for m in seen] == [(1, 0), (0, 1)], seen
    assert path.is_fifo()  # left alone: not replaced, not written into


def test_a_run_whose_cache_entry_is_a_fifo_completes_with_its_floors(tmp_path, compose, smoke):
    cache = tmp_path / "floors"
    cfg = [*smoke, f"log.floor_cache={cache}"]
    run(compose(cfg), tmp_path / "a")
    (entry,) = cache.glob("*.json")
    _fifo_in_place(entry)
    with Unblocker(entry) as watchdog, cache_warnings() as seen:
        result = run(compose(cfg), tmp_path / "b")
    assert not watchdog.used, "the run blocked on the FIFO"
    assert "a FIFO" in seen[0], seen
    assert result.state == "completed"
    a, b = (load_run(tmp_path / d).metadata["theory"] for d in "ab")
    assert b["swarm_floor_source"] == "computed"
    assert without_source(b) == without_source(a)


GET_IN_BOUNDED_MEMORY = """
import json, resource, sys, warnings
from harness.observers import floor_cache

inputs = json.loads(sys.stdin.read())
floors = json.loads(sys.argv[2])
cache = floor_cache.FloorCache(sys.argv[1])
vm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmSize"))
_, hard = resource.getrlimit(resource.RLIMIT_AS)
resource.setrlimit(resource.RLIMIT_AS, (vm * 1024 + (256 << 20), hard))
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    found, source = floor_cache.cached(cache, inputs, lambda: floors)
print(json.dumps({"source": source, "warnings": [str(w.message) for w in seen]}))
"""


def _dev_zero(path: Path) -> None:
    path.unlink()
    path.symlink_to("/dev/zero")


def _huge(path: Path) -> None:
    with open(path, "r+b") as f:  # sparse: 4 GB that take no disk
        f.truncate(4 << 30)


@pytest.mark.parametrize(
    ("replace", "why"),
    [(_dev_zero, "a character device"), (_huge, "more than the")],
    ids=["dev-zero", "4GB"],
)
def test_an_endless_or_huge_entry_is_never_loaded(tmp_path, replace, why):
    """In a process whose address space allows 256 MB more than it holds: reading the
    entry whole would end in MemoryError."""
    observer, n = truth(tmp_path)
    inputs = observer.floor_inputs(n)
    good = record(tmp_path)
    floors = {k: v for k, v in good.items() if not k.startswith("swarm_floor_")}
    (path,) = tmp_path.glob("*.json")
    replace(path)
    proc = subprocess.run(
        [sys.executable, "-c", GET_IN_BOUNDED_MEMORY, str(tmp_path), json.dumps(floors)],
        input=json.dumps(inputs),
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["source"] == "computed"
    assert any(why in w for w in out["warnings"]), out["warnings"]
    if path.is_symlink():  # not replaced: never written through to the device
        assert os.readlink(path) == "/dev/zero"
    else:  # a regular file: replaced by the record, which the next read trusts
        assert path.stat().st_size < 100_000
        with warnings.catch_warnings():
            warnings.simplefilter("error", FloorCacheWarning)
            assert FloorCache(tmp_path).get(inputs) == floors


def _set_floor(key: str, value):
    def damage(path: Path) -> None:
        data = json.loads(path.read_text())
        if value is None:
            del data["floors"][key]
        else:
            data["floors"][key] = value
        data["checksum"] = digest(canonical(data["floors"]))  # the checksum matches
        path.write_text(json.dumps(data))

    return damage


def _swap_band(band: str):
    """Swap a band's lo and hi (an inverted band), the checksum recomputed."""

    def damage(path: Path) -> None:
        data = json.loads(path.read_text())
        floors = data["floors"]
        lo, hi = f"{band}_floor_lo", f"{band}_floor_hi"
        assert float(floors[lo]) < float(floors[hi])  # a real band: the swap inverts it
        floors[lo], floors[hi] = floors[hi], floors[lo]
        data["checksum"] = digest(canonical(floors))
        path.write_text(json.dumps(data))

    return damage


def _nested(path: Path) -> None:
    path.write_text("[" * 200_000)  # within the size cap, deeper than any parser's stack


@pytest.mark.parametrize(
    "damage",
    [
        _set_floor("swarm_l2_floor_mean", "nan"),
        _set_floor("swarm_w2_floor_hi", "inf"),
        _set_floor("swarm_l2_floor_lo", "1e400"),
        _set_floor("swarm_w2_floor_mean", "-0.5"),
        _set_floor("swarm_l2_floor_mean", "0.5000"),
        _set_floor("swarm_l2_floor_hi", "a lot"),
        _set_floor("swarm_w2_floor_draws", "3"),
        _set_floor("swarm_w2_method", "sliced"),
        _set_floor("swarm_w2_floor_lo", None),
        _set_floor("swarm_l2_floor_median", "0.1"),
        _nested,
        _swap_band("swarm_l2"),
        _swap_band("swarm_w2"),
        _set_floor("swarm_l2_floor_mean", "9.0"),
        _set_floor("swarm_w2_floor_mean", "5e-324"),
        _set_floor("swarm_l2_floor_lo", "-0.0"),
    ],
    ids=[
        "nan",
        "inf",
        "overflow",
        "negative",
        "not-shortest-repr",
        "not-a-number",
        "other-draws",
        "other-method",
        "missing-key",
        "extra-key",
        "nested-json",
        "l2-lo-above-hi",
        "w2-lo-above-hi",
        "mean-above-hi",
        "mean-below-lo",
        "negative-zero",
    ],
)
def test_floors_the_computation_cannot_give_are_recomputed_even_under_a_matching_checksum(
    tmp_path, calls, damage
):
    good = record(tmp_path)
    (path,) = tmp_path.glob("*.json")
    damage(path)
    with cache_warnings() as seen:
        again = record(tmp_path)
    assert len(seen) == 1 and "ignoring" in seen[0], seen
    assert len(calls) == 2 and again["swarm_floor_source"] == "computed"
    assert without_source(again) == without_source(good)
    with warnings.catch_warnings():  # rewritten: the next run reads it
        warnings.simplefilter("error", FloorCacheWarning)
        assert record(tmp_path)["swarm_floor_source"] == "cache" and len(calls) == 2


def test_floors_the_computation_cannot_give_are_never_stored(tmp_path):
    observer, n = truth(tmp_path)
    inputs = observer.floor_inputs(n)
    floors = {k: v for k, v in record(None).items() if not k.startswith("swarm_floor_")}
    cache = FloorCache(tmp_path)
    with cache_warnings() as seen:
        assert cache.put(inputs, {**floors, "swarm_l2_floor_mean": "nan"}) is None
    assert len(seen) == 1 and "not storing" in seen[0], seen
    assert not list(tmp_path.iterdir())
    assert cache.put(inputs, floors) is not None


@pytest.mark.parametrize(
    "bad, why",
    [
        ({"swarm_w2_floor_lo": "hi", "swarm_w2_floor_hi": "lo"}, "band is inverted"),
        ({"swarm_l2_floor_mean": "hi+"}, "outside its band"),
        ({"swarm_l2_floor_mean": "lo-"}, "outside its band"),
    ],
    ids=["lo-above-hi", "mean-above-hi", "mean-below-lo"],
)
def test_a_band_the_computation_cannot_give_is_never_stored(tmp_path, bad, why):
    observer, n = truth(tmp_path)
    inputs = observer.floor_inputs(n)
    floors = {k: v for k, v in record(None).items() if not k.startswith("swarm_floor_")}

    def value(band: str, spec: str) -> str:
        lo, hi = (float(floors[f"{band}_floor_{x}"]) for x in ("lo", "hi"))
        return repr({"lo": lo, "hi": hi, "hi+": 2 * hi + 1, "lo-": lo / 2}[spec])

    forged = {k: value(k.split("_floor_")[0], v) for k, v in bad.items()}
    cache = FloorCache(tmp_path)
    with cache_warnings() as seen:
        assert cache.put(inputs, {**floors, **forged}) is None
    assert len(seen) == 1 and "not storing" in seen[0] and why in seen[0], seen
    assert not list(tmp_path.iterdir())


def test_a_run_never_logs_poisoned_floors_from_the_cache(tmp_path, compose, smoke):
    cache = tmp_path / "floors"
    cfg = [*smoke, f"log.floor_cache={cache}"]
    run(compose(cfg), tmp_path / "a")
    (entry,) = cache.glob("*.json")
    _set_floor("swarm_l2_floor_mean", "nan")(entry)
    with cache_warnings() as seen:
        run(compose(cfg), tmp_path / "b")
    assert len(seen) == 1 and "swarm_l2_floor_mean is 'nan'" in seen[0], seen
    run(compose(cfg), tmp_path / "c")
    a, b, c = (load_run(tmp_path / d).metadata["theory"] for d in "abc")
    assert (b["swarm_floor_source"], c["swarm_floor_source"]) == ("computed", "cache")
    assert without_source(a) == without_source(b) == without_source(c)


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_a_sweep_s_status_run_and_lock_files_are_read_without_blocking(tmp_path, kind):
    """A FIFO or /dev/zero in place of a job's ``job_status.json``, the sweep's run file
    or its lock is read as malformed (empty, 0), never opened blocking or read whole."""

    from harness.runs.status import STATUS_FILE, read_status
    from harness.runs.supervision import read_lock
    from harness.runs.sweep_progress import RUN_FILE, read_run

    paths = [tmp_path / STATUS_FILE, tmp_path / RUN_FILE, tmp_path / "lock"]
    for path in paths:
        if kind == "fifo":
            os.mkfifo(path)
        else:
            path.symlink_to("/dev/zero")
    result: list[object] = []
    reader = threading.Thread(
        target=lambda: result.extend(
            [read_status(tmp_path), read_run(tmp_path), read_lock(paths[2]).pid]
        ),
        daemon=True,
    )
    reader.start()
    reader.join(timeout=10)
    assert not reader.is_alive(), "a reader blocked"
    assert result == [{}, {}, 0]
