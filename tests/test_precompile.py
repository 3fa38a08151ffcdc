"""sonarmap._precompile (+ _precompile_record): the pipeline's kernels compiled by several
processes at once on a cold cache."""

from __future__ import annotations

import json
import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

import pytest

import sonarmap._precompile as pc
from sonarmap.survey import executors


def test_types_round_trip() -> None:
    from numba.core import types

    cases = [
        types.Array(types.float32, 2, "C"),
        types.Array(types.uint8, 1, "A", readonly=True),
        types.Array(types.int64, 3, "F"),
        types.float64, types.int64, types.intp, types.boolean, types.none, types.complex128,
        types.literal(0), types.literal(True), types.literal("mode"),
        types.Omitted(3), types.Omitted(None),
        types.UniTuple(types.int64, 3),
        types.Tuple([types.float32, types.Array(types.float64, 1, "C")]),
        types.unicode_type,
    ]
    for t in cases:
        enc = pc.encode_type(t)
        assert json.loads(json.dumps(enc)) == enc  # JSON-able
        assert pc.decode_type(enc) == t, (t, enc)


def test_types_it_cannot_describe_are_refused() -> None:
    from numba.core import types

    with pytest.raises(pc.UnsupportedType):
        pc.encode_type(types.Record.make_c_struct([("a", types.int32)]))
    with pytest.raises(pc.UnsupportedType):
        pc.encode_type(types.Omitted(object()))
    with pytest.raises(pc.UnsupportedType):
        pc.decode_type(["no such kind"])


def test_the_list_is_read_longest_first_and_a_bad_file_is_no_list(tmp_path: Path) -> None:
    entries = pc.load_signatures()
    assert len(entries) >= 30
    seconds = [e.get("seconds", 1.0) for e in entries]
    assert seconds == sorted(seconds, reverse=True)
    assert any(e["kernel"] == "sonarmap.stats._em_kernels:em_general_kernel" for e in entries)
    bad = tmp_path / "s.json"
    bad.write_text("{not json")
    assert pc.load_signatures(bad) == []
    bad.write_text(json.dumps({"signatures": [{"kernel": 3}, {"kernel": "a:b", "args": []}]}))
    assert pc.load_signatures(bad) == [{"kernel": "a:b", "args": []}]
    assert pc.load_signatures(tmp_path / "missing.json") == []


def test_a_queue_compiles_each_entry_once_and_skips_what_it_cannot_build() -> None:
    listed = pc.load_signatures()
    entries = listed[-3:] + [{"kernel": "sonarmap.nowhere:kernel", "args": []},
                             {"kernel": listed[0]["kernel"], "args": [["no such kind"]]}]
    handed = iter(range(100))
    taken: list[int] = []

    def take() -> int:
        taken.append(next(handed))
        return taken[-1]

    assert pc.compile_queue(entries, take) == 3
    assert taken == [0, 1, 2, 3, 4, 5]  # the last index is past the end: the queue is done
    for e in entries[:3]:
        disp = pc.resolve_kernel(e["kernel"])
        assert tuple(pc.decode_type(a) for a in e["args"]) in [tuple(s) for s in disp.signatures]


def test_workers_share_the_queue_only_on_a_cold_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    entries = pc.load_signatures()[-4:]
    monkeypatch.setattr(pc, "load_signatures", lambda: entries)
    ctx = multiprocessing.get_context("spawn")
    # warm: the first worker marks the queue done, nobody compiles
    monkeypatch.setattr(pc, "cache_is_cold", lambda: False)
    counter = ctx.Value("i", -1)
    assert executors._precompile_share(counter, 2) is None
    assert counter.value == len(entries)
    assert executors._precompile_share(counter, 2) is None
    # cold: the first worker takes the whole queue here; a second one finds it done
    monkeypatch.setattr(pc, "cache_is_cold", lambda: True)
    counter = ctx.Value("i", -1)
    assert executors._precompile_share(counter, 2) == len(entries)
    assert counter.value == len(entries) + 1
    assert executors._precompile_share(counter, 2) is None
    # one worker, or no counter: nothing to share
    assert executors._precompile_share(ctx.Value("i", -1), 1) is None
    assert executors._precompile_share(None, 2) is None


@pytest.mark.slow
def test_an_empty_cache_is_cold(tmp_path: Path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    code = "import sonarmap._precompile as pc; print(pc.cache_is_cold())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["True"]
    # the kernel it looks at compiled here (into the suite's cache): not cold
    entry = next(e for e in pc.load_signatures() if e["kernel"].endswith(":pooled_kept_edges"))
    assert pc.compile_entry(entry)
    assert not pc.cache_is_cold()


@pytest.mark.slow
def test_the_list_is_what_the_warm_up_compiles() -> None:
    """A fresh process's warm-ups and simulated pings call exactly the listed entry points
    (else: rewrite the list with `python -m sonarmap._precompile_record`) - under the numba version
    that recorded it (another version may type an argument differently: then the list is only a
    hint, its entries that do not build are skipped, and this test says nothing)."""
    import numba

    recorded = json.loads(pc.SIGNATURES_FILE.read_text(encoding="utf-8")).get("numba")
    if recorded != numba.__version__:
        pytest.skip(f"the list was recorded with numba {recorded}, this is {numba.__version__}")
    res = subprocess.run([sys.executable, "-m", "sonarmap._precompile_record", "--check"], capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_helpers_share_the_queue_with_the_calling_process(monkeypatch: pytest.MonkeyPatch) -> None:
    entries = pc.load_signatures()[-5:]
    monkeypatch.setattr(pc, "load_signatures", lambda: entries)
    monkeypatch.setattr(pc, "cache_is_cold", lambda: False)
    assert pc.compile_with_helpers(1) == 0  # warm: nothing started
    monkeypatch.setattr(pc, "cache_is_cold", lambda: True)
    assert pc.compile_with_helpers(0) == 0
    monkeypatch.setenv("SONARMAP_COMPILE_HELPERS", "0")  # (the suite's own setting)
    assert pc.compile_with_helpers() == 0
    seen: list[tuple[float, float]] = []
    # a helper process takes part of the queue; both done
    assert pc.compile_with_helpers(1, progress=lambda taken, total: seen.append((taken, total))) == 1
    total = sum(e.get("seconds", 1.0) for e in entries)
    assert seen and all(t == pytest.approx(total) for _, t in seen)
    assert [t for t, _ in seen] == sorted(t for t, _ in seen) and seen[-1][0] == pytest.approx(total)
    # (the entries the helper took are compiled in its process, into the cache, not in this one)


def test_an_interrupt_stops_the_helpers(monkeypatch: pytest.MonkeyPatch) -> None:
    entries = pc.load_signatures()[-2:]
    monkeypatch.setattr(pc, "load_signatures", lambda: entries)
    monkeypatch.setattr(pc, "cache_is_cold", lambda: True)
    started: list[multiprocessing.process.BaseProcess] = []
    real = multiprocessing.get_context

    class Ctx:
        def __init__(self, method: str) -> None:
            self.ctx = real(method)

        def Value(self, *a: object) -> object:  # noqa: N802 - multiprocessing's name
            return self.ctx.Value(*a)

        def Process(self, **kw: object) -> multiprocessing.process.BaseProcess:  # noqa: N802
            kw["target"] = _sleep_forever
            kw["args"] = ()
            p = self.ctx.Process(**kw)
            started.append(p)
            return p

    monkeypatch.setattr(multiprocessing, "get_context", Ctx)

    def interrupted(entries: object, take: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(pc, "compile_queue", interrupted)
    with pytest.raises(KeyboardInterrupt):
        pc.compile_with_helpers(1)
    assert len(started) == 1
    started[0].join(10)
    assert not started[0].is_alive()


def _sleep_forever() -> None:  # pragma: no cover - runs in a helper process
    import time

    time.sleep(600)
