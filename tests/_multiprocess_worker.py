"""One process of a `jax.distributed` run of `jaxmc.integrate`, for tests/test_multiprocess.py.

    python tests/_multiprocess_worker.py PORT NUM_PROCESSES PROCESS_ID

With NUM_PROCESSES > 1 the process joins the others through the coordinator at
localhost:PORT (CPU collectives over gloo); with 1 it runs alone. It prints one
JSON line: per method, the estimate's mean and variance (float.hex, exact) and n.
Exit status 3 means the processes could not run a collective at all.
"""

import json
import sys

import jax


PROBE_FAILED = 3
METHODS = ("plain", "qmc", "adaptive", "importance", "auto")


def main(port: int, processes: int, index: int) -> None:
    jax.config.update("jax_enable_x64", True)
    if processes > 1:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=f"localhost:{port}", num_processes=processes, process_id=index,
            initialization_timeout=60,
        )
        try:  # one cross-process collective: are gloo collectives there at all?
            from jax.experimental import multihost_utils

            multihost_utils.process_allgather(jax.numpy.arange(2) + index)
        except Exception as error:  # noqa: BLE001 (reported to the test, which skips)
            print(f"{type(error).__name__}: {error}", file=sys.stderr)
            sys.exit(PROBE_FAILED)

    import jax.numpy as jnp

    import jaxmc

    def f(x):  # a ridge along the diagonal
        y = x - 0.5
        return jnp.exp(-500.0 * (jnp.sum(y**2) - jnp.sum(y) ** 2 / 3) - 10.0 * jnp.sum(y) ** 2)

    lo, hi = jnp.zeros(3), jnp.ones(3)
    results = {"devices": len(jax.devices()), "processes": jax.process_count()}
    for method in METHODS:
        est = jaxmc.integrate(jax.random.key(7), f, lo, hi, n=200_000, method=method, chunk=2**15)
        results[method] = {
            "mean": float(est.mean).hex(),
            "variance": float(est.variance).hex(),
            "n": int(est.n),
            "method": est.method,
        }
    print(json.dumps(results))
    if processes > 1:
        jax.distributed.shutdown()


if __name__ == "__main__":
    main(*map(int, sys.argv[1:4]))
