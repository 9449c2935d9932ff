"""`integrate` across processes: JAX's multi-process runtime is how jaxmc runs on a cluster.

Two processes on this machine, joined by `jax.distributed.initialize` (CPU
collectives over gloo, one device each), must give the estimate of one process
with two devices bit for bit: the same blocks on the same devices, merged by the
same collectives. Each process is a subprocess running tests/_multiprocess_worker.py.
"""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from .helpers import subprocess_xla_flags


WORKER = Path(__file__).with_name("_multiprocess_worker.py")
PROBE_FAILED = 3  # the worker's exit status when no cross-process collective runs
TIMEOUT = 300  # seconds per process; a run takes ~20 s of CPU per process


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def _launch(port: int, processes: int, index: int, devices: int) -> subprocess.Popen:
    env = {
        **os.environ,
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": subprocess_xla_flags(devices),
    }
    return subprocess.Popen(
        [sys.executable, str(WORKER), str(port), str(processes), str(index)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )


def _results(runs: list[subprocess.Popen]) -> list[dict]:
    outputs = []
    try:
        for run in runs:
            stdout, stderr = run.communicate(timeout=TIMEOUT)
            outputs.append((run.returncode, stdout, stderr))
    finally:
        for run in runs:
            if run.poll() is None:
                run.kill()
                run.communicate()
    for status, _, stderr in outputs:
        if status == PROBE_FAILED:
            pytest.skip(f"gloo CPU collectives unavailable in this jaxlib: {stderr.strip()[-300:]}")
    for status, _, stderr in outputs:
        assert status == 0, stderr[-3000:]
    # gloo prints its connection messages on stdout before the worker's JSON line.
    return [json.loads(stdout.strip().splitlines()[-1]) for _, stdout, _ in outputs]


@pytest.mark.slow
def test_two_processes_give_one_process_estimate():
    port = _free_port()
    runs = [_launch(port, 2, index, devices=1) for index in range(2)]
    runs.append(_launch(0, 1, 0, devices=2))  # one process, two devices, started alongside
    first, second, alone = _results(runs)
    assert first["processes"] == second["processes"] == 2 and first["devices"] == 2
    assert alone["processes"] == 1 and alone["devices"] == 2
    # (The VEGAS+ stream by "adaptive", randomised QMC by "qmc", the i.i.d. stream from a
    # fitted density by "importance", and the pilot of "auto".)
    for method in ("plain", "qmc", "adaptive", "importance", "auto"):
        assert first[method] == second[method] == alone[method], method
