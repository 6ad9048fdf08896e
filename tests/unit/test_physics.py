"""The MuJoCo hall and the 6-DOF arm: every model compiles and steps without warnings, the arm
matches its DH table, the IK reaches the whole cell, and the controller picks reliably."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest

from domain import hall
from domain import work_cell as g
from domain.arm import ARM_XML, HOME_Q, JOINTS, SERVO_LAG_S, arm_model
from domain.controller import PickController
from domain.hall import arena_mb, build_mjcf, build_model, object_pool_size
from domain.kinematics import ArmKinematics
from domain.world import CHECK_PERIOD_US, World, spawn_plan
from fabric import native
from scenario.schema import ScenarioError, parse_scenario
from services.physics.ideal_loop import run_ideal
from services.physics.stepper import LIBRARY, NativeStepAhead, StepAhead, Stepper, step_ahead

# UR5e-class DH table (Universal Robots' published kinematics parameters): a, d, alpha, link mass.
DH_A = [0.0, -0.425, -0.3922, 0.0, 0.0, 0.0]
DH_D = [0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996]
DH_ALPHA = [np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0]
LINK_MASS = [3.761, 8.058, 2.846, 1.37, 1.3, 0.365]
VARIED = {"object_yaw_spread_deg": 180, "object_size_spread_m": 0.01, "object_mass_spread_kg": 0.2,
          "object_jitter_s": 0.4}


def dh_flange(q: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    for i in range(6):
        ct, st = np.cos(q[i]), np.sin(q[i])
        ca, sa = np.cos(DH_ALPHA[i]), np.sin(DH_ALPHA[i])
        t = t @ np.array([[ct, -st * ca, st * sa, DH_A[i] * ct], [st, ct * ca, -ct * sa, DH_A[i] * st],
                          [0, sa, ca, DH_D[i]], [0, 0, 0, 1]])
    return t


def no_warnings(data: mujoco.MjData) -> bool:
    return all(w.number == 0 for w in data.warning)


# ---- models -------------------------------------------------------------------------------------
def test_arm_model_compiles_and_holds_home_for_10_s_without_warnings() -> None:
    model = mujoco.MjModel.from_xml_path(str(ARM_XML))
    data = mujoco.MjData(model)
    data.qpos[:] = data.ctrl[:] = HOME_Q
    for _ in range(int(10 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    assert no_warnings(data), [w.number for w in data.warning]
    assert np.abs(data.qpos - HOME_Q).max() < 1e-3  # gravity compensated, servos hold


@pytest.mark.parametrize("loops", [1, 4])
def test_hall_mjcf_compiles_and_steps_10_s_without_warnings(loops: int) -> None:
    sc = parse_scenario({"loops": loops})
    model = mujoco.MjModel.from_xml_string(build_mjcf(sc))  # the composed hall is plain MJCF
    assert model.nu == 6 * loops and model.neq == loops * object_pool_size(sc)  # a grip weld per part
    data = mujoco.MjData(model)
    for _ in range(int(10 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    assert no_warnings(data), [w.number for w in data.warning]
    assert np.isfinite(data.qpos).all()


@pytest.mark.slow
def test_the_largest_hall_of_the_family_compiles_with_an_arena_that_grows_with_its_cells() -> None:
    """240 work cells of the family's slowest, densest corner (0.1 m/s, a part every 2 +- 0.6 s:
    17 pool parts a cell, 25 920 degrees of freedom), where MuJoCo's default arena, growing with
    their square, could not be reserved."""
    hall = {"work_cells_per_row": 16, "work_cell_pitch_m": [4.0, 4.0]}
    cell = {"belt_speed_m_s": 0.1, "object_period_s": 2.0, "object_jitter_s": 0.6}
    small = build_model(parse_scenario({"loops": 2, "hall": hall, "work_cell": cell}))
    assert small.narena == arena_mb(2) * 2**20
    model = build_model(parse_scenario({"loops": 240, "hall": hall, "work_cell": cell}))
    assert model.nv == 240 * 6 * (1 + 17) and model.narena == arena_mb(240) * 2**20
    data = mujoco.MjData(model)
    for _ in range(10):
        mujoco.mj_step(model, data)
    assert no_warnings(data), [w.number for w in data.warning]


def test_world_with_varied_parts_steps_10_s_without_warnings() -> None:
    sc = parse_scenario({"loops": 2, "duration_s": 10, "work_cell": VARIED})
    world = World(sc)
    plan = sorted((t, i, kw) for i in range(2) for t, kw in spawn_plan(sc, np.random.default_rng(3), 1000))
    for t, i, kw in plan:
        world.advance_to(t)
        world.spawn(i, **kw)
    world.advance_to(10_000_000)
    assert no_warnings(world.data), [w.number for w in world.data.warning]
    assert np.abs(world.data.qpos[world.cells[1].qadr] - HOME_Q).max() < 1e-3
    rows = world.finish()
    assert rows and all(r["outcome"] in ("missed", "unfinished") for r in rows)  # nobody picked


def test_arm_matches_the_dh_table() -> None:
    model = arm_model()
    data = mujoco.MjData(model)
    flange = model.body("cup").id  # the tool body sits on the flange, frame {6}
    rng = np.random.default_rng(0)
    for q in [np.zeros(6), *rng.uniform(-3, 3, (5, 6))]:
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        t = dh_flange(q)
        assert np.allclose(data.xpos[flange], t[:3, 3], atol=1e-6)
        assert np.allclose(data.xmat[flange].reshape(3, 3), t[:3, :3], atol=1e-6)
    assert [model.joint(i).name for i in range(model.njnt)] == list(JOINTS)
    masses = [model.body(f"link{i}").mass[0] for i in range(1, 7)]
    assert np.allclose(masses, LINK_MASS)
    # every servo: kv / kp = SERVO_LAG_S (the lag the controller compensates)
    kp, kv = model.actuator_gainprm[:, 0], -model.actuator_biasprm[:, 2]
    assert np.allclose(kv / kp, SERVO_LAG_S)
    assert (model.body_gravcomp[model.body("link1").id:] == 1).all()  # every moving body


def test_home_posture_and_ik_cover_the_cell() -> None:
    kin = ArmKinematics()
    rot = np.array(g.TOOL_DOWN)
    p, r = kin.fk(HOME_Q)
    assert np.allclose(p, g.HOME_TOOL_POS, atol=1e-3) and np.allclose(r, rot, atol=1e-3)
    q = np.array(HOME_Q)
    px, py = g.PLATFORM_CENTRE
    targets = [(x, y, z) for x in np.linspace(*g.PICK_X_RANGE, 5) for y in (-0.08, 0.08)
               for z in (0.76, 0.95)] + [(px, py, 0.8), (px, py, 1.0), g.HOME_TOOL_POS]
    for target in targets:  # along straight moves, as the controller drives them
        start = kin.fk(q)[0]
        for s in np.linspace(0, 1, 25):
            q, err = kin.solve(start + s * (np.asarray(target) - start), rot, q, iters=20, tol=1e-8)
        assert err < 1e-6, target
        assert np.linalg.svd(kin.jacobian(q), compute_uv=False)[-1] > 0.05, target  # no singularity


def test_solve_many_gives_solve_s_joints_to_the_bit() -> None:
    """Seeds near and far from the targets (one step, several, capped steps, joint limits): each
    arm's joints and error norm as ``solve`` gives them alone."""
    kin = ArmKinematics()
    rot = np.array(g.TOOL_DOWN)
    rng = np.random.default_rng(3)
    for spread_q, spread_p in [(0.02, 0.0), (0.02, 0.01), (0.3, 0.01), (0.3, 0.2), (1.5, 0.5)]:
        q0 = np.array(HOME_Q) + rng.normal(0, spread_q, (40, 6))
        p = np.array([kin.tcp_position(q) for q in q0]) + rng.normal(0, spread_p, (40, 3))
        q_many, err_many = kin.solve_many(p, rot, q0)
        for i in range(40):
            q, err = kin.solve(p[i], rot, q0[i])
            assert q.tobytes() == q_many[i].tobytes() and err == err_many[i]


def test_tcp_positions_give_tcp_position_to_the_bit() -> None:
    kin = ArmKinematics()
    qs = np.random.default_rng(5).uniform(kin.lo, kin.hi, (200, kin.nq))
    many = kin.tcp_positions(qs)
    assert all(kin.tcp_position(q).tobytes() == row.tobytes() for q, row in zip(qs, many, strict=True))


def test_controller_taken_apart_commands_what_step_commands() -> None:
    """The cups' positions in one call, plan, one ``solve_many`` over the arms, then command:
    the joints ``step`` gives."""
    sc = parse_scenario({"loops": 1})
    whole = [PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S) for _ in range(3)]
    apart = [PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S) for _ in range(3)]
    kin = ArmKinematics()
    for ctl in whole + apart:
        ctl.on_state(list(HOME_Q), False)
    for t in range(10_000, 3_000_000, 10_000):
        tracks = [[{"id": 0, "t_us": t, "p": [-0.3 + 0.2 * t / 1e6, 0.03 * (i - 1), 0.78],
                    "v": [0.2, 0.0, 0.0]}] for i in range(3)]
        expected = []
        for ctl, tr in zip(whole, tracks, strict=True):
            ctl.on_estimate(tr)
            expected.append(ctl.step(t))
        tips = kin.tcp_positions(np.array([c.q for c in apart]))
        for ctl, tr, tip in zip(apart, tracks, tips, strict=True):
            ctl.on_estimate(tr)
            ctl.plan(t, tip)
        qs, errs = kin.solve_many(np.array([c.p_sp for c in apart]), apart[0].rot,
                                  np.array([c.q_sp for c in apart]))
        for ctl, q, err, (q_exp, suction), other in zip(apart, qs, errs.tolist(), expected, whole,
                                                        strict=True):
            cmd = ctl.command(q, err)
            assert cmd.tobytes() == q_exp.tobytes() and ctl.suction == suction
            ctl.on_state(cmd.tolist(), False)
            other.on_state(q_exp.tolist(), False)
    assert {c.phase for c in whole} != {"home"}  # the arms moved through the state machine


# ---- scenario fields ----------------------------------------------------------------------------
def test_part_spreads_are_validated() -> None:
    with pytest.raises(ScenarioError, match="object_size_spread_m"):
        parse_scenario({"work_cell": {"object_size_m": 0.06, "object_size_spread_m": 0.05}})
    with pytest.raises(ScenarioError, match="object_mass_spread_kg"):
        parse_scenario({"work_cell": {"object_mass_kg": 0.3, "object_mass_spread_kg": 0.3}})
    sc = parse_scenario({"work_cell": {**VARIED, "object_lateral_spread_m": 0.05}, "duration_s": 60})
    plan = spawn_plan(sc, np.random.default_rng(1), sc.physics_timestep_us)
    sizes = [kw["size_m"] for _, kw in plan]
    assert len(plan) == 15 and 0.05 <= min(sizes) and max(sizes) <= 0.07
    assert all(abs(kw["y_offset_m"]) <= 0.05 for _, kw in plan)
    assert all(b - a >= 4_000_000 - 800_000 for (a, _), (b, _) in zip(plan, plan[1:], strict=False))


def test_spawn_times_are_rounded_to_the_microsecond_not_truncated() -> None:
    sc = parse_scenario({"work_cell": {"object_period_s": 4.1, "first_object_s": 0.7}, "duration_s": 9})
    assert [t for t, _ in spawn_plan(sc, np.random.default_rng(1), 1000)] == [700_000, 4_800_000, 8_900_000]


def test_a_command_for_no_work_cell_or_with_no_number_is_refused() -> None:
    world = World(parse_scenario({"loops": 2}))
    with pytest.raises(ValueError, match=r"work cell -1: the hall has work cells 0..1"):
        world.command(-1, list(HOME_Q), False)
    with pytest.raises(ValueError, match=r"work cell 2: the hall has work cells 0..1"):
        world.command(2, list(HOME_Q), False)
    with pytest.raises(ValueError, match="cell 0: command has a non-finite joint target"):
        world.command(0, [float("nan"), *HOME_Q[1:]], False)
    ctrl = world.data.ctrl.copy()
    world.command(1, list(HOME_Q), True)  # a good one still goes through
    assert world.cells[1].suction and np.array_equal(world.data.ctrl[world.cells[0].act], ctrl[world.cells[0].act])


def test_belt_phases_spread_the_first_parts_and_keep_the_period() -> None:
    """With ``first_object_spread_s`` each cell's first part comes later by its own draw, the
    parts after it a period apart; without it the stream is drawn as before."""
    spread = {"object_period_s": 4.0, "first_object_s": 0.5, "first_object_spread_s": 4.0}
    sc = parse_scenario({"work_cell": spread, "duration_s": 30})
    firsts = [spawn_plan(sc, np.random.default_rng(s), 1000)[0][0] for s in range(40)]
    assert all(500_000 <= t <= 4_500_000 for t in firsts)
    assert max(firsts) - min(firsts) > 2_000_000  # the belts are out of phase, not bunched
    plan = spawn_plan(sc, np.random.default_rng(7), 1000)
    assert {b - a for (a, _), (b, _) in zip(plan, plan[1:], strict=False)} == {4_000_000}
    flat = parse_scenario({"work_cell": {"object_period_s": 4.0, "first_object_s": 0.5}, "duration_s": 30})
    same = parse_scenario({"work_cell": {**spread, "first_object_spread_s": 0.0}, "duration_s": 30})
    assert spawn_plan(flat, np.random.default_rng(7), 1000) == spawn_plan(same, np.random.default_rng(7), 1000)
    with pytest.raises(ScenarioError, match="first_object_spread_s"):
        parse_scenario({"work_cell": {"first_object_spread_s": -1.0}})


# ---- picking --------------------------------------------------------------------------------------
class SnapshotWorld(World):
    """A world that keeps every body's pose after each ``advance_to``, with sleeping on or off."""

    sleep = True

    def __init__(self, sc: Any) -> None:
        super().__init__(sc)
        bit = int(mujoco.mjtEnableBit.mjENBL_SLEEP)
        self.model.opt.enableflags = self.model.opt.enableflags | bit if self.sleep else self.model.opt.enableflags & ~bit
        self.poses: list[tuple[int, bytes]] = []

    def advance_to(self, t_us: int) -> None:
        super().advance_to(t_us)
        d = self.data
        self.poses.append((self.t_us, d.qpos.tobytes() + d.qvel.tobytes() + d.xpos.tobytes() + d.xquat.tobytes()))


def test_parked_parts_sleep_and_change_nothing() -> None:
    """Only parked pool parts sleep (the hall steps faster); every body's pose and velocity after
    every step is that of stepping with sleeping off, to the bit, spawns and placements included."""
    sc = parse_scenario({"loops": 4, "detailed_loops": 0, "duration_s": 10.0, "seed": 11})
    runs = {}
    for sleep in (False, True):
        SnapshotWorld.sleep = sleep
        world = SnapshotWorld(sc)
        runs[sleep] = (world, run_ideal(sc, world=world))
    (off, off_result), (on, on_result) = runs[False], runs[True]
    hall = mujoco.MjModel.from_xml_string(build_mjcf(sc))
    assert hall.opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    assert [t["outcome"] for t in on_result.tasks].count("placed") >= 8
    assert on_result.tasks == off_result.tasks
    assert len(on.poses) == len(off.poses) and on.poses == off.poses
    parked = {on.model.body_treeid[c.obj_body[s]] for c in on.cells for s in c.free_slots}
    in_play = {on.model.body_treeid[c.obj_body[s]] for c in on.cells for s in c.active}
    assert parked and all(on.data.tree_asleep[t] >= 0 for t in parked)  # asleep
    assert all(on.data.tree_asleep[t] < 0 for t in in_play)  # awake
    assert on.data.nv_awake < on.model.nv


def make_stepper(kind: str, world: World) -> Stepper:
    if kind == "python":
        return StepAhead(world, "physics-step")
    if native.library(LIBRARY) is None:
        pytest.skip("no fresh native build here (make native)")
    stepper = step_ahead(world, "physics-step")
    assert isinstance(stepper, NativeStepAhead)
    return stepper


class SteppedWorld(World):
    """A world whose every ``mj_step`` runs in a stepper's thread, as many steps a handover as
    the world allows (``steps_alone``; the Python stepper takes one): every other handover is
    taken back by polling, and while one runs the observations must show the state at its start."""

    def __init__(self, sc: Any, kind: str) -> None:
        super().__init__(sc)
        self.stepper = make_stepper(kind, self)
        self.handovers: list[int] = []

    def advance_to(self, t_us: int) -> None:
        while self.t_us + self.dt_us <= t_us:
            seen = [(self.joint_state(i), self.objects(i)) for i in range(len(self.cells))]
            self.stepper.start(t_us, self.steps_alone())
            self.handovers.append(self.stepper.end_us - self.t_us)
            assert [(self.joint_state(i), self.objects(i)) for i in range(len(self.cells))] == seen
            if len(self.handovers) % 2:
                while self.stepper.busy():
                    pass
                while not self.stepper.poll():  # the flag may come just before the handover's end
                    pass
            else:
                self.stepper.wait()
            assert not self.stepper.running


@pytest.mark.parametrize("kind", ["python", "native"])
def test_a_stepper_steps_the_world_exactly_as_advance_to(kind: str) -> None:
    """Picks and places with the steps' mj_step in the stepper's thread: the same tasks, the same
    state to the bit; observations held while a step runs."""
    sc = parse_scenario({"loops": 2, "duration_s": 8, "work_cell": {**VARIED, "object_period_s": 3.0}})
    plain, threaded = World(sc), SteppedWorld(sc, kind)
    plain_result, threaded_result = run_ideal(sc, world=plain), run_ideal(sc, world=threaded)
    placed = [t for t in plain_result.tasks if t["outcome"] == "placed"]
    assert len(placed) >= 2  # the steps covered suction seals and releases
    assert threaded_result.tasks == plain_result.tasks
    assert threaded.t_us == plain.t_us
    for name in ("qpos", "qvel", "act", "ctrl", "eq_active"):
        assert getattr(threaded.data, name).tobytes() == getattr(plain.data, name).tobytes(), name
    if kind == "native":  # several steps a handover where no cup waited to seal
        assert min(threaded.handovers) == sc.physics_timestep_us < max(threaded.handovers) <= CHECK_PERIOD_US
    stepper = threaded.stepper
    stepper.start(threaded.t_us + threaded.dt_us)
    stepper.close()  # waits for the running step
    assert not stepper._thread.is_alive()  # type: ignore[attr-defined]


def test_a_handover_of_several_steps_holds_each_steps_observations() -> None:
    """The native stepper's handover of several steps: the state at each step's start is held
    for its observers as soon as that step has begun, and the world ends as stepped one by one."""
    sc = parse_scenario({"loops": 3, "duration_s": 2})
    plain, threaded = World(sc), World(sc)
    for world in (plain, threaded):
        for cell in range(3):
            world.spawn(cell)
        world.advance_to(153_000)  # the parts ride their belts; no cup waits to seal
    steps = threaded.steps_alone()
    assert steps == CHECK_PERIOD_US // sc.physics_timestep_us - 3  # up to the next task check
    expected = []
    for _ in range(steps):
        expected.append([(plain.joint_state(i), plain.objects(i)) for i in range(3)])
        plain.advance_to(plain.t_us + plain.dt_us)
    stepper = make_stepper("native", threaded)
    start = threaded.t_us
    stepper.start(start + 50_000, steps)
    assert stepper.end_us == start + steps * sc.physics_timestep_us
    for k in range(steps):
        t_us = start + k * sc.physics_timestep_us + 400  # inside step k
        stepper.reach(t_us)
        threaded.observe_at(t_us)
        assert [(threaded.joint_state(i), threaded.objects(i)) for i in range(3)] == expected[k], k
    stepper.wait()
    assert not stepper.busy() and not stepper.running
    assert threaded.t_us == plain.t_us
    for name in ("qpos", "qvel"):
        assert getattr(threaded.data, name).tobytes() == getattr(plain.data, name).tobytes(), name
    with pytest.raises(RuntimeError, match="no state held"):
        threaded.observe_at(start)  # observations come in time order: that one is gone
    stepper.close()


def test_the_python_stepper_hands_back_its_steps_error_once(monkeypatch: pytest.MonkeyPatch) -> None:
    world = World(parse_scenario({"loops": 1, "duration_s": 1}))
    stepper = make_stepper("python", world)
    stepper.wait()  # nothing running: returns at once
    stepper.start(world.t_us + world.dt_us)
    assert stepper.running
    with pytest.raises(RuntimeError, match="running already"):
        stepper.start(world.t_us + world.dt_us)
    stepper.wait()
    assert world.t_us == world.dt_us and not stepper.running

    def broken(model: Any, data: Any) -> None:
        raise ValueError("no such step")

    monkeypatch.setattr(mujoco, "mj_step", broken)
    stepper.start(world.t_us + world.dt_us)
    with pytest.raises(ValueError, match="no such step"):
        stepper.wait()
    stepper.wait()  # the error is raised once
    assert world.t_us == world.dt_us  # the failed step did not count
    stepper.close()
    assert not stepper._thread.is_alive()  # type: ignore[attr-defined]


@pytest.mark.parametrize("kind", ["python", "native"])
def test_mujocos_error_in_a_step_is_raised_by_either_stepper(kind: str, monkeypatch: pytest.MonkeyPatch,
                                                              tmp_path: Path) -> None:
    """An arena too small for three parts' contacts: MuJoCo's error comes back as an exception
    where the steps are taken back, and the process goes on (MuJoCo alone would end it)."""
    monkeypatch.chdir(tmp_path)  # MuJoCo's warnings go to MUJOCO_LOG.TXT in the working directory
    build = hall._hall_xml
    monkeypatch.setattr(hall, "_hall_xml", lambda sc: re.sub(r'<size memory="\d+M"/>', '<size memory="8K"/>', build(sc)))
    world = World(parse_scenario({"loops": 1, "detailed_loops": 0}))
    stepper = make_stepper(kind, world)
    for k in range(3):
        world.spawn(0, y_offset_m=0.05 * (k - 1))
    with pytest.raises(mujoco.FatalError, match="mj_stackAlloc: out of memory"):
        for t_us in range(1000, 50_000, 1000):
            stepper.start(t_us, world.steps_alone())
            stepper.wait()
    stepper.wait()  # raised once
    stepper.close()
    assert not stepper._thread.is_alive()  # type: ignore[attr-defined]


def test_observations_during_a_step_show_its_start_before_the_belt_drive() -> None:
    sc = parse_scenario({"loops": 1, "duration_s": 2})
    world = World(sc)
    world.spawn(0)
    world.advance_to(200_000)  # the part rides the belt
    before = world.objects(0)
    assert before and before[0]["v"][0] > 0
    world.data.qvel[:] = 0.0  # so that the belt drive at the step's start changes the velocities
    before = world.objects(0)
    stepper = make_stepper("python", world)
    stepper.start(world.t_us + world.dt_us)
    assert world.objects(0) == before  # velocities as before the belt drive, positions as before the step
    stepper.wait()
    after = world.objects(0)
    assert after[0]["v"][0] == pytest.approx(sc.work_cell.belt_speed_m_s) and after[0]["p"] != before[0]["p"]
    stepper.close()


def test_ended_tasks_are_taken_up_to_a_time() -> None:
    sc = parse_scenario({"loops": 2, "duration_s": 8, "work_cell": {"object_period_s": 3.0}})
    world = World(sc)
    run_ideal(sc, world=world)
    rows = [t.row() for t in world.tasks]  # every task has ended: unfinished ones at the run's end
    ends = sorted({r["end_us"] for r in rows})
    assert len(ends) >= 3
    taken = world.take_ended(ends[1])
    assert taken and taken == [r for r in rows if r["end_us"] <= ends[1]]
    assert world.take_ended(ends[1]) == []  # taken once
    assert world.take_ended(ends[-1]) == [r for r in rows if r["end_us"] > ends[1]]


def test_controller_places_every_part_with_ideal_poses() -> None:
    """Ground-truth pose at each camera frame, no delay: every part placed (>= 10 tasks)."""
    sc = parse_scenario({"loops": 4, "duration_s": 14, "work_cell": {**VARIED, "object_period_s": 3.0}})
    res = run_ideal(sc)
    assert len(res.tasks) >= 10
    assert all(t["outcome"] == "placed" for t in res.tasks), [t for t in res.tasks if not t["success"]]
    assert all(t["grasp_attempts"] == 1 for t in res.tasks)


def test_each_grasp_attempt_is_charged_to_the_part_under_the_cup() -> None:
    """A part every 1.5 s keeps several on each belt: every part the arm sealed on had at least
    one attempt of its own."""
    sc = parse_scenario({"loops": 2, "duration_s": 14, "work_cell": {"object_period_s": 1.5}})
    res = run_ideal(sc)
    grasped = [t for t in res.tasks if t["grasp_us"] is not None]
    assert len(grasped) >= 6 and len(grasped) < len(res.tasks)  # some parts were never reached
    assert all(t["grasp_attempts"] >= 1 for t in grasped), grasped


def test_delay_compensation_matters_at_200_ms() -> None:
    sc = parse_scenario({"loops": 2, "duration_s": 14, "work_cell": {"object_period_s": 3.0}})
    compensated = run_ideal(sc, delay_us=200_000)
    naive = run_ideal(sc.model_copy(update={"robot": sc.robot.model_copy(update={"delay_compensation": False})}),
                      delay_us=200_000)
    assert len(compensated.tasks) >= 6
    assert compensated.success_rate == 1.0
    assert naive.success_rate < 0.5


def test_stale_estimates_make_the_arm_hold_instead_of_descending() -> None:
    sc = parse_scenario({"loops": 1})
    ctl = PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S)
    ctl.on_state(list(HOME_Q), False)
    track = {"id": 0, "t_us": 0, "p": [-0.3, 0.0, 0.78], "v": [0.2, 0.0, 0.0]}
    ctl.on_estimate([track])
    ctl.step(10_000)
    assert ctl.phase == "approach"
    for k in range(2, 100):  # no fresh estimate after t = 0: older than 400 ms from t = 410 ms
        ctl.step(k * 10_000)
    assert ctl.phase == "approach" and not ctl.suction and ctl.holds > 50


@pytest.mark.slow
def test_ideal_network_success_over_200_tasks() -> None:
    """The benchmark-style version: >= 200 tasks with varied parts, >= 99% placed (about a
    minute on two shared cores)."""
    sc = parse_scenario({"loops": 8, "duration_s": 106, "seed": 7, "work_cell": VARIED})
    res = run_ideal(sc)
    assert len(res.tasks) >= 200
    assert res.success_rate >= 0.99, [t for t in res.tasks if not t["success"]]


def test_a_cell_camera_draws_the_same_pixels_without_the_cells_it_cannot_see() -> None:
    """Rendering leaves out the other cells only when none of them (nor its shadow) can be in
    view: the frames are the same to the bit as the whole hall's, and a neighbour brought into
    view is drawn."""
    sc = parse_scenario({"loops": 3, "detailed_loops": 1})
    world = World(sc)
    try:
        w, h = sc.camera.width_px, sc.camera.height_px
        for at, part in spawn_plan(sc, np.random.default_rng(3), sc.physics_timestep_us)[:3]:
            world.advance_to(at)
            world.spawn(0, **part)
        world.advance_to(world.t_us + 500_000)
        view = world._camera.view
        hidden = view.out_of_view(world.data, 0, "c0_camera", w / h)
        assert hidden is not None and len(hidden) > 0 and set(view.cell_of[hidden]) == {1, 2}
        rgb, depth = world.render(0, w, h)
        view.usable = False  # the whole hall, as drawn before
        rgb_all, depth_all = world.render(0, w, h)
        assert depth is not None and depth_all is not None
        assert np.array_equal(rgb, rgb_all) and np.array_equal(depth, depth_all)
        view.usable = True
        # A neighbour's part moved under the camera is in view: nothing is left out.
        part = world.cells[1].obj_qadr[0]
        world.data.qpos[part:part + 3] = [*world.cells[0].origin[:2], 1.0]
        mujoco.mj_forward(world.model, world.data)
        assert view.out_of_view(world.data, 0, "c0_camera", w / h) is None
    finally:
        world.close()
