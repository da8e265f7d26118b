"""Registration in worker processes: register_node's `workers` setting above 1.

Python threads share one interpreter lock, and small_gicp and Open3D hold it while they run (GICP's
covariances, k-d trees and alignment, the scores' searches), so registrations on threads of one process do
not run side by side (figures: docs/ros_node.md, "Pairing and load"). So each worker is a process with its
own `Registrar`.

`RemoteRegistrar` is that process seen from the node: `register`, `config` and `num_points` as the
core's `Registrar` (the node's `genreg_ros.registrar.Registering`), one pair at a time. The two clouds go to
the worker and the aligned cloud comes back through shared-memory blocks (one copy each way, grown when a
larger cloud arrives); everything else (the initial guess, the rest of the result, errors, and the settings
when `config` was assigned since the last pair) goes through a pipe. A `GenRegError` raised in
the worker is raised again in the caller with its class and message; a worker that dies raises
`WorkerError` and is started again at the next `register`.
"""

from __future__ import annotations

import multiprocessing as mp
import signal
import time
from dataclasses import replace
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from typing import TYPE_CHECKING, Any

import numpy as np

from genreg_core import errors
from genreg_core.config import RegistrationConfig

if TYPE_CHECKING:
    from genreg_core.result import RegistrationResult

START_TIMEOUT_S = 300.0  # loading torch, the model and the compiled kernels (a cold numba cache: ~30 s)
GROWTH = 1.25  # a shared-memory block that is too small is replaced by one this much larger than needed


class WorkerError(RuntimeError):
    """A registration worker process could not start, or died; one-line message."""


def _layout(array: np.ndarray, offset: int) -> tuple[str, tuple[int, ...], int]:
    return array.dtype.str, array.shape, offset


def _view(block: SharedMemory, layout: tuple[str, tuple[int, ...], int]) -> np.ndarray:
    dtype, shape, offset = layout
    return np.ndarray(shape, np.dtype(dtype), buffer=block.buf, offset=offset)


class RemoteRegistrar:
    """A `genreg_core.registration.Registrar` in its own process (spawned; daemon). Not thread-safe: one
    caller thread per instance. `start()` launches the process, `wait_ready()` waits for its model (start
    several, then wait for each, and they load side by side): a worker is ready once it has loaded its model
    (`registrar.round_trip` then warms it with a synthetic pair through `register`); `close()` ends it."""

    def __init__(self, checkpoint: str, config: RegistrationConfig, num_points: int | None = None,
                 name: str = "genreg_worker") -> None:
        self.config = config
        self._sent: RegistrationConfig | None = None  # the settings the worker holds
        self._args = (checkpoint, num_points)
        self._name = name
        self._num_points: int | None = None
        self._conn: Connection | None = None
        self._proc: mp.process.BaseProcess | None = None
        self._blocks: dict[str, SharedMemory | None] = {"in": None, "out": None}

    @property
    def num_points(self) -> int:
        if self._num_points is None:
            raise WorkerError(f"{self._name} is not ready")
        return self._num_points

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def start(self) -> None:
        ctx = mp.get_context("spawn")  # never fork a process that runs rclpy's and torch's threads
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, *self._args, self.config), name=self._name,
                                 daemon=True)
        self._proc.start()
        self._sent = self.config
        child.close()

    def wait_ready(self, timeout: float = START_TIMEOUT_S) -> None:
        """Wait until the worker has loaded its model; the worker's own error (e.g. CheckpointError) is
        raised here."""
        reply = self._receive(timeout)
        if reply[0] != "ready":
            self.close()
            _raise(reply)
        self._num_points = reply[1]

    def register(self, source: np.ndarray, target: np.ndarray,
                 initial_guess: np.ndarray | None = None) -> RegistrationResult:
        """`Registrar.register` in the worker: the same RegistrationResult, or the same GenRegError. The
        settings travel with the pair only when `config` is not the object the worker last received."""
        if not self.alive:
            self.close()  # died since the last pair: start afresh
            self.start()
            self.wait_ready()
        source, target = np.ascontiguousarray(source), np.ascontiguousarray(target)
        inline = source.dtype.hasobject or target.dtype.hasobject  # not raw memory: let the core reject it
        clouds: tuple[Any, Any]
        if inline:
            clouds = (source, target)
        else:
            block = self._block("in", source.nbytes + target.nbytes)
            clouds = (_layout(source, 0), _layout(target, source.nbytes))
            for array, layout in zip((source, target), clouds, strict=True):
                _view(block, layout)[...] = array
        out = self._block("out", 12 * len(source))  # the aligned cloud: float32 (K, 3), K <= len(source)
        config = None if self.config is self._sent else self.config
        self._conn.send(("register", self._blocks["in"].name if not inline else None, out.name, clouds,
                         initial_guess, config))
        self._sent = self.config
        reply = self._receive(None)
        if reply[0] != "result":
            _raise(reply)
        result, aligned_shape = reply[1], reply[2]
        result.aligned_source = _view(out, ("<f4", aligned_shape, 0)).copy()  # the block is reused next pair
        return result

    def close(self) -> None:
        """End the worker (waits up to 5 s, then terminates it) and free the shared memory."""
        if self._conn is not None:
            try:
                self._conn.send(("close",))
            except (OSError, ValueError):
                pass
        if self._proc is not None:
            self._proc.join(5.0)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(5.0)
        if self._conn is not None:
            self._conn.close()
        self._conn, self._proc, self._num_points = None, None, None
        for role, block in self._blocks.items():
            if block is not None:
                block.close()
                block.unlink()
            self._blocks[role] = None

    def _block(self, role: str, size: int) -> SharedMemory:
        """The `role` block, replaced by a larger one when it holds fewer than `size` bytes."""
        block = self._blocks[role]
        if block is None or block.size < size:
            if block is not None:
                block.close()
                block.unlink()
            block = self._blocks[role] = SharedMemory(create=True, size=max(int(GROWTH * size), 4096))
        return block

    def _receive(self, timeout: float | None) -> tuple:
        """The worker's next reply; WorkerError if it dies (or, with a timeout, stays silent) first."""
        start = time.monotonic()
        while not self._conn.poll(1.0):
            if not self._proc.is_alive():
                code = self._proc.exitcode
                self.close()
                raise WorkerError(f"{self._name} process exited (code {code})")
            if timeout is not None and time.monotonic() - start > timeout:
                self.close()
                raise WorkerError(f"{self._name} process did not answer within {timeout:.0f} s")
        try:
            return self._conn.recv()
        except (EOFError, OSError) as exc:
            self.close()
            raise WorkerError(f"{self._name} process exited ({type(exc).__name__})") from None


def _raise(reply: tuple) -> None:
    """Raise the worker's error: a genreg_core error as its own class, anything else as WorkerError."""
    _, kind, message = reply
    cls = getattr(errors, kind, None)
    if isinstance(cls, type) and issubclass(cls, errors.GenRegError):
        raise cls(message)
    raise WorkerError(f"registration worker: {kind}: {message}")


def _attach(attached: dict[str, SharedMemory], role: str, name: str) -> SharedMemory:
    """The block `name` (the caller's, who unlinks it), attached once; a replaced block is let go."""
    block = attached.get(role)
    if block is not None and block.name == name:
        return block
    if block is not None:
        try:
            block.close()
        except BufferError:  # a view of it is still alive somewhere: it goes with the process
            pass
    # Registered with the caller's resource tracker (spawned children share it): a set, so no second entry;
    # the caller's unlink removes it.
    block = attached[role] = SharedMemory(name=name)
    return block


def _serve(conn: Connection, checkpoint: str, num_points: int | None, config: RegistrationConfig) -> None:
    """The worker process: load the model, then register pairs until told to close or the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the node, which closes its workers
    from genreg_core import kernels
    from genreg_core.memory import retain_freed_memory
    from genreg_core.registration import Registrar

    retain_freed_memory()
    try:
        registrar = Registrar.from_checkpoint(checkpoint, config=config, num_points=num_points)
        kernels.compile_all()
    except Exception as exc:  # noqa: BLE001 (reported to the caller, who raises it)
        conn.send(("error", type(exc).__name__, str(exc)))
        return
    conn.send(("ready", registrar.num_points))
    attached: dict[str, SharedMemory] = {}
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message[0] != "register":
            return
        _, in_name, out_name, clouds, guess, config = message
        if config is not None:  # new settings (else those of the last pair)
            registrar.config = config
        try:
            if in_name is not None:
                block = _attach(attached, "in", in_name)
                clouds = tuple(_view(block, layout) for layout in clouds)
            result = registrar.register(*clouds, initial_guess=guess)
            del clouds
            aligned = result.aligned_source
            _view(_attach(attached, "out", out_name), ("<f4", aligned.shape, 0))[...] = aligned
            reply = ("result", replace(result, aligned_source=aligned[:0]), aligned.shape)
        except Exception as exc:  # noqa: BLE001 (one bad pair must not end the worker)
            reply = ("error", type(exc).__name__, str(exc))
        conn.send(reply)
