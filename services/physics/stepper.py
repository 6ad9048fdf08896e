"""A thread that steps the world ahead while the group's thread processes the other members' events.

``mj_step`` releases the GIL, so a step in another thread runs on the second core. The work is
handed over once a simulated millisecond at 32 loops. ``NativeStepAhead`` (the default where the
native build is fresh) runs ``mj_step`` in a thread of C code that never takes the GIL
(``native_stepper.c``): the step's Python parts (the conveyor drive before it, seals and task
checks after) run in the caller's thread, and a handover is a semaphore post and a wait, with no
thread waiting for the GIL held by the other. ``StepAhead`` is the pure-Python way: a Python
thread runs ``advance(t_us)``, handed over with three locks used as binary semaphores (``acquire``
waits in C with the GIL released and a ``release`` from the other thread wakes it); that thread
must take the GIL from the busy group's thread around every step, so each handover costs the
group's thread more.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
from collections.abc import Callable
from typing import Protocol

import mujoco

from domain.world import World
from fabric import native

# The native build's library (fabric.native.LIBRARIES) that holds the C thread.
LIBRARY = "cosim5g_stepper"


class Stepper(Protocol):
    """What the physics federate asks of a step-ahead thread."""

    running: bool

    def start(self, t_us: int) -> None: ...

    def wait(self) -> None: ...

    def close(self) -> None: ...


def step_ahead(world: World, name: str) -> Stepper:
    """The native stepper of ``world`` where the native build and libmujoco load, else the
    Python one."""
    lib, mj_step = native.library(LIBRARY), _mj_step_address()
    if lib is None or mj_step is None:
        return StepAhead(world.advance_to, name)
    return NativeStepAhead(world, lib, mj_step, name)


def _mj_step_address() -> int | None:
    """Where ``mj_step`` is in the libmujoco the bindings loaded (not another copy of it)."""
    for path in glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*")):
        try:
            lib = ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
        except OSError:
            continue
        return ctypes.cast(lib.mj_step, ctypes.c_void_p).value
    return None


class NativeStepAhead:
    """Runs one step of ``world`` at a time in a C thread: ``start`` does the step's Python part
    before ``mj_step`` and hands the step over, ``wait`` takes it back and does the part after.
    The caller touches the world only between ``wait`` and the next ``start``."""

    def __init__(self, world: World, lib: ctypes.CDLL, mj_step: int, name: str) -> None:
        ptr = ctypes.c_void_p
        lib.cosim_stepper_new.restype = ptr
        lib.cosim_stepper_new.argtypes = [ptr, ptr, ptr]
        for fn in (lib.cosim_stepper_serve, lib.cosim_stepper_go, lib.cosim_stepper_wait,
                   lib.cosim_stepper_stop, lib.cosim_stepper_free):
            fn.restype, fn.argtypes = None, [ptr]
        self._world, self._lib = world, lib
        self._handle = lib.cosim_stepper_new(mj_step, world.model._address, world.data._address)
        if not self._handle:
            raise MemoryError("native stepper: no memory for its semaphores")
        self.running = False
        # A ctypes call releases the GIL for as long as it runs: the thread's whole life here.
        self._thread = threading.Thread(target=lib.cosim_stepper_serve, args=(self._handle,),
                                        name=name, daemon=True)
        self._thread.start()

    def start(self, t_us: int) -> None:
        """Begin the world's next step if it ends by ``t_us`` (the caller's event steps on from
        there)."""
        if self.running:
            raise RuntimeError("a step ahead is running already")
        world = self._world
        if world.t_us + world.dt_us > t_us:
            return
        world.before_step()
        self._lib.cosim_stepper_go(self._handle)
        self.running = True

    def wait(self) -> None:
        """Wait for the running step, if any, and end it."""
        if not self.running:
            return
        self._lib.cosim_stepper_wait(self._handle)
        self.running = False
        self._world.after_step()

    def close(self) -> None:
        """Wait for the running step (the world is not stepped on) and end the thread."""
        if self.running:
            self._lib.cosim_stepper_wait(self._handle)
            self.running = False
        self._lib.cosim_stepper_stop(self._handle)
        self._thread.join(timeout=10)
        if not self._thread.is_alive():
            self._lib.cosim_stepper_free(self._handle)


class StepAhead:
    """Runs ``advance(t_us)`` in a thread of its own, one call at a time."""

    def __init__(self, advance: Callable[[int], None], name: str) -> None:
        self._advance = advance
        self._go, self._started, self._done = threading.Lock(), threading.Lock(), threading.Lock()
        for lock in (self._go, self._started, self._done):
            lock.acquire()  # each is released by one side and taken by the other
        self._target = 0
        self._error: BaseException | None = None
        self._closing = False
        self.running = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def start(self, t_us: int) -> None:
        """Begin ``advance(t_us)``; returns once it holds the GIL, so that it starts now rather than
        when the caller next lets go of the GIL (it lets go inside ``mj_step``)."""
        if self.running:
            raise RuntimeError("a step ahead is running already")
        self._target = t_us
        self.running = True
        self._go.release()
        self._started.acquire()

    def wait(self) -> None:
        """Wait for the running call, if any; its exception is raised here."""
        if not self.running:
            return
        self._done.acquire()
        self.running = False
        error, self._error = self._error, None
        if error is not None:
            raise error

    def close(self) -> None:
        """Wait for the running call (its error is not raised again) and end the thread."""
        if self.running:
            self._done.acquire()
            self.running = False
        self._closing = True
        self._go.release()
        self._thread.join(timeout=10)

    def _loop(self) -> None:
        while True:
            self._go.acquire()
            if self._closing:
                return
            self._started.release()
            try:
                self._advance(self._target)
            except BaseException as exc:  # handed to the caller's thread by ``wait``
                self._error = exc
            self._done.release()
