"""What register_node registers with: the `Registering` contract and the registrars that meet it.

Two kinds meet it: the core's `genreg_core.registration.Registrar` in the node's own process (`workers` 1)
and `genreg_ros.workers.RemoteRegistrar`, a Registrar in a worker process of its own (`workers` > 1).
`load_registrars` loads one per worker, each warmed up with a synthetic pair before it is returned, and
`close_registrars` ends the worker processes.
"""

from __future__ import annotations

import threading
from typing import TYPE_CHECKING, Protocol

import numpy as np

from genreg_core.config import RegistrationConfig
from genreg_core.errors import GenRegError
from genreg_ros.workers import RemoteRegistrar

if TYPE_CHECKING:
    from genreg_core.result import RegistrationResult


class Registering(Protocol):
    """What the node calls on a registrar. One caller thread at a time."""

    config: RegistrationConfig  # the settings the next `register` uses; the node assigns it only when it changes

    @property
    def num_points(self) -> int:
        """The model's N: points per cloud fed to the network."""
        ...

    def register(self, source: np.ndarray, target: np.ndarray,
                 initial_guess: np.ndarray | None = None) -> RegistrationResult:
        """Register `source` onto `target` (from `initial_guess`, T_target_source, if given); a GenRegError
        for a pair that cannot be registered."""
        ...


class LoadError(RuntimeError):
    """The model cannot be loaded (a bad checkpoint, a device torch lacks, a worker that did not start);
    one line."""


def load_registrars(checkpoint: str, config: RegistrationConfig, num_points: int | None,
                    workers: int) -> list[Registering]:
    """One registrar per worker: the core's Registrar in this process (`workers` 1), else a worker process
    each (started side by side, after this process has compiled the kernels), each warmed up with a synthetic
    pair before it is returned (`Registrar.warm_up` in this process; for worker processes through the node's
    hand-over, `round_trip`). LoadError if one cannot be loaded (the processes
    started are closed)."""
    from genreg_core import kernels
    from genreg_core.registration import Registrar

    remote = [RemoteRegistrar(checkpoint, config, num_points, f"genreg_worker_{k}") for k in range(workers)] \
        if workers > 1 else []
    try:
        # The compiled kernels first (decoding uses them), not at the first pair; the workers started after
        # load them from numba's cache instead of compiling them three times at once (a fresh install: ~50 s).
        kernels.compile_all()
        for r in remote:
            r.start()
        for r in remote:
            r.wait_ready()
        if remote:
            round_trip(remote)
            return list(remote)
        local = Registrar.from_checkpoint(checkpoint, config=config, num_points=num_points)
        local.warm_up()  # as `round_trip` warms worker processes
        return [local]
    except GenRegError as exc:
        close_registrars(remote)
        raise LoadError(str(exc)) from None
    except (RuntimeError, AssertionError, OSError) as exc:  # e.g. a cuda device on a CPU-only torch
        close_registrars(remote)
        raise LoadError(f"cannot load model {checkpoint!r}: {exc}") from None


def round_trip(remote: list[RemoteRegistrar]) -> None:
    """Warm every worker at once, as `Registrar.warm_up` warms an in-process one: its synthetic pair (PDSAC's
    modes included) through the way the node hands pairs over (shared memory, the pipe, the result back), so
    the first real pair pays no first-call costs on either side. Each worker's settings are restored."""
    from genreg_core.registration import warm_up_config, warm_up_pair

    pair = warm_up_pair()

    def warm(r: RemoteRegistrar) -> None:
        settings = r.config
        r.config = warm_up_config(settings)
        try:
            r.register(*pair)
        finally:
            r.config = settings

    threads = [threading.Thread(target=warm, args=(r,), daemon=True) for r in remote]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()


def close_registrars(registrars: list[Registering]) -> None:
    """End the worker processes among `registrars` (an in-process Registrar needs nothing)."""
    for r in registrars:
        if isinstance(r, RemoteRegistrar):
            r.close()
