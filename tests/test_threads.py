"""The CLI's single-threaded BLAS (sonarmap._threads), checked in fresh interpreters."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from sonarmap._threads import THREAD_ENV_VARS

pytestmark = pytest.mark.slow  # every test spawns interpreters

_PROBE = (
    "import json\n"
    "from sonarmap._threads import limit_blas_threads\n"
    "did = limit_blas_threads()\n"
    "from threadpoolctl import threadpool_info\n"
    "print(json.dumps([did, [d['num_threads'] for d in threadpool_info() if d['user_api'] == 'blas']]))\n"
)


def _probe(env_extra: dict[str, str]) -> tuple[bool, list[int]]:
    env = {k: v for k, v in os.environ.items() if k not in THREAD_ENV_VARS}
    env.update(env_extra)
    r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr
    did, threads = json.loads(r.stdout)
    return bool(did), list(threads)


def test_blas_runs_single_threaded_unless_the_user_chose() -> None:
    did, threads = _probe({})
    assert did and threads and all(t == 1 for t in threads)
    did, threads = _probe({"OPENBLAS_NUM_THREADS": "2"})
    assert not did


@pytest.mark.parametrize("var", THREAD_ENV_VARS)
def test_each_thread_variable_is_respected(var: str) -> None:
    assert _probe({var: "2"})[0] is False
