"""Step-ahead threads: the world steps on while the group's thread processes other members' events.

Only ``mj_step`` runs in the thread, a C one (``NativeStepAhead``) or a Python one handed each
step with two locks used as binary semaphores (``StepAhead``); the step's Python parts run in the
caller's. Why: docs/architecture.md sec. 3, "Groups"; what the caller observes meanwhile:
docs/physics.md, "Belt, parts and outcomes".
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
from typing import Protocol

import mujoco
import numpy as np

from domain.world import World
from fabric import native

# The native build's library (fabric.native.LIBRARIES) that holds the C thread.
LIBRARY = "cosim5g_stepper"


class Stepper(Protocol):
    """What the physics federate asks of a step-ahead thread: ``start`` begins the world's next
    steps, none ending after ``t_us``; until ``wait`` or ``poll`` ends them the caller must not
    change the world, and observes the state of any time before ``end_us`` once ``reach`` has
    returned for it (``World.observe_at``)."""

    running: bool
    end_us: int

    def start(self, t_us: int, steps: int = 1) -> None: ...

    def wait(self) -> None: ...

    def reach(self, t_us: int) -> None: ...

    def busy(self) -> bool: ...

    def poll(self) -> bool: ...

    def close(self) -> None: ...


def step_ahead(world: World, name: str) -> Stepper:
    """The native stepper of ``world`` where the native build and libmujoco load, else the
    Python one."""
    lib, mj_step = native.library(LIBRARY), _mj_step_address()
    if lib is None or mj_step is None:
        return StepAhead(world, name)
    return NativeStepAhead(world, lib, mj_step, name)


def _libmujoco() -> ctypes.CDLL | None:
    """The libmujoco the bindings loaded (not another copy of it)."""
    for path in glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*")):
        try:
            return ctypes.CDLL(path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
        except OSError:
            continue
    return None


def _mj_step_address() -> int | None:
    """Where ``mj_step`` is in the libmujoco the bindings loaded."""
    lib = _libmujoco()
    return None if lib is None else ctypes.cast(lib.mj_step, ctypes.c_void_p).value


class _SplitStep:
    """A step's Python parts in the caller's thread, its ``mj_step`` handed to another thread
    (``_go`` hands steps over, ``_join`` waits for them)."""

    max_steps = 1  # steps one handover may hold

    def __init__(self, world: World) -> None:
        self._world = world
        self.running = False
        self.steps = 0  # of the running handover
        self.end_us = 0  # when the running handover's last step ends

    def _go(self, steps: int) -> None:
        raise NotImplementedError

    def _join(self) -> None:
        raise NotImplementedError

    def _try_join(self) -> bool:
        raise NotImplementedError

    def _check(self) -> None:
        """Raise the ended step's error, if it had one."""

    def start(self, t_us: int, steps: int = 1) -> None:
        """Begin the world's next steps, as many as ``steps`` and ``max_steps`` allow with none
        ending after ``t_us`` (none if the next one would); more than one only as the world
        allows them with nothing in Python between them (``World.steps_alone``)."""
        if self.running:
            raise RuntimeError("a step ahead is running already")
        world = self._world
        steps = min(steps, self.max_steps, (t_us - world.t_us) // world.dt_us)
        if steps < 1:
            return
        world.hold_observations()
        world.before_step()
        self._go(steps)
        self.running, self.steps, self.end_us = True, steps, world.t_us + steps * world.dt_us

    def reach(self, t_us: int) -> None:
        """Wait until the running handover holds the state at ``t_us`` (before ``end_us``): the
        step in which it falls has begun."""

    def busy(self) -> bool:
        """Whether steps handed over still run (without ending them: ``poll`` does)."""
        return self.running and not self._finished()

    def _finished(self) -> bool:
        raise NotImplementedError

    def wait(self) -> None:
        """Wait for the running steps, if any, and end them (their error is raised here)."""
        if not self.running:
            return
        self.running = False
        self._join()
        self._check()
        self._end()

    def poll(self) -> bool:
        """End the running steps if they have ended, without waiting; whether none runs now."""
        if not self.running:
            return True
        if not self._try_join():
            return False
        self.running = False
        self._check()
        self._end()
        return True

    def _end(self) -> None:
        self._world.release_observations()
        self._world.after_steps(self.steps)

    def close(self) -> None:
        """Wait for the running steps (the world is not stepped on: their error is not raised)
        and end the thread."""
        if self.running:
            self.running = False
            self._join()
            self._world.release_observations()
        self._shut_down()

    def _shut_down(self) -> None:
        raise NotImplementedError


class NativeStepAhead(_SplitStep):
    """Runs the steps' ``mj_step`` in a C thread, several steps a handover: between them the
    thread applies the conveyor drive and copies the state for the steps' observers."""

    max_steps = 64

    def __init__(self, world: World, lib: ctypes.CDLL, mj_step: int, name: str) -> None:
        super().__init__(world)
        ptr, long = ctypes.c_void_p, ctypes.c_long
        lib.cosim_stepper_new.restype = ptr
        lib.cosim_stepper_new.argtypes = [ptr, ptr, ptr, ptr, ptr, long, long]
        lib.cosim_stepper_go.restype = None
        lib.cosim_stepper_go.argtypes = [ptr, ctypes.c_int, ptr, long, ctypes.c_double, ptr, ptr]
        lib.cosim_stepper_wait_steps.restype = None
        lib.cosim_stepper_wait_steps.argtypes = [ptr, ctypes.c_int]
        for fn in (lib.cosim_stepper_serve, lib.cosim_stepper_wait, lib.cosim_stepper_stop,
                   lib.cosim_stepper_free):
            fn.restype, fn.argtypes = None, [ptr]
        lib.cosim_stepper_try_wait.restype, lib.cosim_stepper_try_wait.argtypes = ctypes.c_int, [ptr]
        lib.cosim_stepper_finished_flag.restype, lib.cosim_stepper_finished_flag.argtypes = ptr, [ptr]
        lib.cosim_stepper_error.restype, lib.cosim_stepper_error.argtypes = ctypes.c_char_p, [ptr]
        lib.cosim_stepper_catch_errors.restype, lib.cosim_stepper_catch_errors.argtypes = None, [ptr]
        self._lib = lib
        mujoco_lib = _libmujoco()
        if mujoco_lib is not None:  # MuJoCo's errors in the thread's steps are raised here
            lib.cosim_stepper_catch_errors(ctypes.addressof(ctypes.c_void_p.in_dll(mujoco_lib, "mju_user_error")))
        qpos, qvel = world.data.qpos, world.data.qvel
        self._handle = lib.cosim_stepper_new(mj_step, world.model._address, world.data._address,
                                             qpos.ctypes.data, qvel.ctypes.data, qpos.size, qvel.size)
        if not self._handle:
            raise MemoryError("native stepper: no memory for its semaphores and locks")
        self._done_flag = ctypes.c_int.from_address(lib.cosim_stepper_finished_flag(self._handle))
        self._handed: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # alive while running
        # A ctypes call releases the GIL for as long as it runs: the thread's whole life here.
        self._thread = threading.Thread(target=lib.cosim_stepper_serve, args=(self._handle,),
                                        name=name, daemon=True)
        self._thread.start()

    def _go(self, steps: int) -> None:
        if steps == 1:
            self._lib.cosim_stepper_go(self._handle, 1, None, 0, 0.0, None, None)
            return
        world = self._world
        belt, speed = world.belt_drive()
        held_qpos, held_qvel = world.hold_ahead(steps)
        self._handed = (belt, held_qpos, held_qvel)
        self._lib.cosim_stepper_go(self._handle, steps, belt.ctypes.data, belt.size, speed,
                                   held_qpos.ctypes.data, held_qvel.ctypes.data)

    def reach(self, t_us: int) -> None:
        world = self._world
        k = (t_us - world.t_us) // world.dt_us  # steps of this handover before the one at t_us
        if k >= 1:
            self._lib.cosim_stepper_wait_steps(self._handle, k)
            if self._lib.cosim_stepper_error(self._handle):
                self.wait()  # the handover ended in an error, raised there

    def _join(self) -> None:
        self._lib.cosim_stepper_wait(self._handle)
        self._handed = None

    def _check(self) -> None:
        error = self._lib.cosim_stepper_error(self._handle)
        if error:
            raise mujoco.FatalError(error.decode(errors="replace"))

    def _finished(self) -> bool:
        return self._done_flag.value != 0

    def _try_join(self) -> bool:
        if not self._lib.cosim_stepper_try_wait(self._handle):
            return False
        self._handed = None
        return True

    def _shut_down(self) -> None:
        self._lib.cosim_stepper_stop(self._handle)
        self._thread.join(timeout=10)
        if not self._thread.is_alive():
            self._lib.cosim_stepper_free(self._handle)


class StepAhead(_SplitStep):
    """Runs each step's ``mj_step`` in a Python thread."""

    def __init__(self, world: World, name: str) -> None:
        super().__init__(world)
        self._go_lock, self._done = threading.Lock(), threading.Lock()
        for lock in (self._go_lock, self._done):
            lock.acquire()  # each is released by one side and taken by the other
        self._error: BaseException | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _go(self, steps: int) -> None:
        self._go_lock.release()

    def _join(self) -> None:
        self._done.acquire()

    def _try_join(self) -> bool:
        return self._done.acquire(blocking=False)

    def _finished(self) -> bool:
        return not self._done.locked()

    def _check(self) -> None:
        error, self._error = self._error, None
        if error is not None:
            raise error

    def _shut_down(self) -> None:
        self._closing = True
        self._go_lock.release()
        self._thread.join(timeout=10)

    def _loop(self) -> None:
        world = self._world
        while True:
            self._go_lock.acquire()
            if self._closing:
                return
            try:
                mujoco.mj_step(world.model, world.data)
            except BaseException as exc:  # handed to the caller's thread by ``wait``
                self._error = exc
            self._done.release()
