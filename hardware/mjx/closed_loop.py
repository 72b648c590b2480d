"""The closed loop of the MJX simulator: every world in CURRENT mode, driven by a ``Policy``.

``MjxSimulator.run_closed_loop`` (implemented by ``run`` here) drives the worlds at 1 kHz: a
``Policy`` (pure JAX functions of one world's parameters, state and ``Observation``, vmapped
over worlds here; the simulator knows nothing of the control law behind it) maps each measured
sample to motor currents; the torque is current / true ratio (effort-clamped), pushes act on
the end effector (``PushSchedule``), and the faults of the CPU Simulator and the ``Arm``
(joint limit, effort, overspeed, refused command: ``faults``) or the policy's own stop put a
world in POSITION mode, holding. The same chunked scan and sharding as the open-loop
``runner``; only the final policy state need leave the device (``ClosedLoopResult``).

Agreement with ``control.loop.run_control`` in lock step on the CPU Simulator (same truth and
impedance controller, no noise, 1.5 s of tracking with a push and an effort fault): max |q|
7.6e-10 rad, |dq| 5.7e-9 rad/s, |current| 3.9e-7 A, tracking RMS to 1e-11 m
(``CLOSED_LOOP_AGREEMENT``). Units: rad, rad/s, A, N, m, s.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxcomp.constants import CONTROL_PERIOD
from jaxcomp.errors import InputError
from jaxcomp.hardware.interaction import Push
from jaxcomp.hardware.mjx.chunks import PyTree, over_worlds, scan_decimated
from jaxcomp.hardware.mjx.faults import (
    FAULT_EFFORT,
    FAULT_LIMIT,
    FAULT_OVERSPEED,
    FAULT_REFUSED,
    FAULT_STOPPED,
)
from jaxcomp.hardware.mjx.mesh import SHARED, WORLDS, placement, world_padding
from jaxcomp.hardware.mjx.model import WORLD_MODEL_FIELDS
from jaxcomp.hardware.mjx.runner import SETTLE_STEPS
from jaxcomp.hardware.mjx.step import implicitfast_step
from jaxcomp.hardware.mjx.truth import BatchTruth

if TYPE_CHECKING:
    from jaxcomp.hardware.mjx.simulator import MjxSimulator

#: Tolerances of ``run_closed_loop`` against the CPU Simulator + ``run_control`` (measured
#: over 1.5 s: 7.6e-10 rad, 5.7e-9 rad/s, 3.9e-7 A, command 3.9e-7 A, tracking RMS 4.5e-11 m).
CLOSED_LOOP_AGREEMENT = {"q": 1e-8, "dq": 1e-7, "current": 5e-6, "rms": 1e-9}


class Observation(NamedTuple):
    """What a closed-loop policy sees of one world at time t (one 1 kHz sample).

    Attributes:
        t: () s since the start of the closed loop (sample k is at k CONTROL_PERIOD).
        q: (n,) rad; dq: (n,) rad/s; current: (n,) A, measured (r tau_applied + noise).
        reference: (m,) row k of the run's shared ``reference`` (e.g. a target trajectory).
    """

    t: jax.Array
    q: jax.Array
    dq: jax.Array
    current: jax.Array
    reference: jax.Array


#: ``init(params, obs) -> state``: a world's policy state from its params and sample 0.
PolicyInit = Callable[[PyTree, Observation], PyTree]
#: ``step(params, state, obs) -> (current, state, stop)``: see ``Policy``.
PolicyStep = Callable[[PyTree, PyTree, Observation], tuple[jax.Array, PyTree, jax.Array]]


class Policy(NamedTuple):
    """A controller of one world, as the MJX closed loop runs it: the protocol between the
    simulator and a control law (the simulator knows nothing else of it).

    Both functions are pure JAX; the simulator vmaps them over worlds and compiles them into
    its chunk function (one compile per ``Policy``, params/state structure and shapes).
    ``params`` and ``state`` are one world's pytrees of arrays (slices of the run's (W, ...)
    ``params`` and state); ``obs`` is the world's ``Observation`` at sample k (t = k
    CONTROL_PERIOD s; q rad, dq rad/s, current A, the reference row k).

    Attributes:
        init: ``init(params, obs_0) -> state``, the state at sample 0; None: the run's
            ``state`` argument gives each world's initial state.
        step: ``step(params, state, obs_k) -> (current, state, stop)``: current (n,) A, the
            motor currents of step k (sent unless NaN/inf or beyond the arm's current limit,
            which faults the world); the state after sample k; stop () bool, True to end the
            world's run before this command is sent (it then holds in POSITION mode).
    """

    init: PolicyInit | None
    step: PolicyStep


class PushSchedule(NamedTuple):
    """Forces on each world's end effector (``hardware.interaction.Push``, force only).

    Push p of world w acts with ``force[w, p]`` (3,) N, world frame, at the end-effector
    site while ``start[w, p] <= t < start[w, p] + duration[w, p]`` (s since the start of the
    closed loop); active pushes add up.
    """

    start: np.ndarray  # (W, P) s
    duration: np.ndarray  # (W, P) s
    force: np.ndarray  # (W, P, 3) N

    @classmethod
    def from_pushes(cls, pushes: Sequence[Sequence[Push]]) -> PushSchedule:
        """A schedule of pushes, world by world.

        Args:
            pushes: one list of ``Push`` (force only) per world.

        Returns:
            The schedule, padded with zero forces to the longest list.

        Raises:
            InputError: no world, or a push with a torque.
        """
        if not pushes:
            raise InputError("pushes is empty: give one list of Push per world")
        width = max(1, max(len(p) for p in pushes))
        start, dur = np.zeros((len(pushes), width)), np.ones((len(pushes), width))
        force = np.zeros((len(pushes), width, 3))
        for w, world in enumerate(pushes):
            for k, push in enumerate(world):
                if np.any(getattr(push, "torque", np.zeros(3))):
                    raise InputError("the MJX simulator applies push forces only (torque = 0)")
                start[w, k], dur[w, k], force[w, k] = push.start, push.duration, push.force
        return cls(start, dur, force)

    def checked(self, worlds: int) -> PushSchedule:
        """The schedule checked for ``worlds`` worlds.

        Args:
            worlds: W.

        Returns:
            The schedule as float arrays: start, duration (W, P) s, force (W, P, 3) N.

        Raises:
            InputError: other shapes, a value not finite, start < 0 or duration <= 0.
        """
        start, dur, force = (np.asarray(a, dtype=float) for a in self)
        if start.ndim != 2 or start.shape[0] != worlds or dur.shape != start.shape:
            raise InputError(
                f"push start and duration must have shape ({worlds}, P), got {start.shape} "
                f"and {dur.shape}"
            )
        if force.shape != start.shape + (3,):
            raise InputError(f"push force must have shape {start.shape + (3,)}, got {force.shape}")
        if not (np.isfinite(start).all() and np.isfinite(dur).all() and np.isfinite(force).all()):
            raise InputError("pushes must be finite")
        if (start < 0).any() or (dur <= 0).any():
            raise InputError("pushes need start >= 0 s and duration > 0 s")
        return PushSchedule(start, dur, force)


class ClosedLoopResult(NamedTuple):
    """What ``MjxSimulator.run_closed_loop`` returns (host arrays; R recorded samples).

    Attributes:
        t: (R,) s, time of each recorded sample (step i's state, at (i + 1) CONTROL_PERIOD).
        q: (W, R, n) rad; dq: (W, R, n) rad/s; current: (W, R, n) A measured, the state after
            steps 0, every, ...; command: (W, R, n) A, the policy's command applied in those
            steps (its last one once the world is in POSITION mode). None when not recorded.
        state: the policy state of every world at the end (pytree of (W, ...) arrays; frozen
            after the last sample whose command was sent).
        q_start: (W, n) rad, each world's settled pose at t = 0.
        fault_step: (W,) the sample at which each world went to POSITION mode after a fault,
            a refused command or a stop (t = fault_step CONTROL_PERIOD; it holds from step
            fault_step on), -1 if none.
        fault_code: (W,) bits ``FAULT_*`` of that event (0 if none).
        every: the recording decimation (0: nothing recorded).
    """

    t: np.ndarray
    q: np.ndarray | None
    dq: np.ndarray | None
    current: np.ndarray | None
    command: np.ndarray | None
    state: PyTree
    q_start: np.ndarray
    fault_step: np.ndarray
    fault_code: np.ndarray
    every: int


def run(
    sim: MjxSimulator,
    truth: BatchTruth,
    policy: Policy,
    params: PyTree,
    state: PyTree | None,
    steps: int,
    *,
    reference: np.ndarray | None = None,
    pushes: PushSchedule | None = None,
    initial_pose: str | Sequence[float] | np.ndarray | None = None,
    settle_steps: int = SETTLE_STEPS,
    seed: int = 0,
    every: int = 0,
    progress: Callable[[int, int], None] | None = None,
    world_ids: Sequence[int] | np.ndarray | None = None,
) -> ClosedLoopResult:
    """Drive every world in CURRENT mode with ``policy`` for ``steps`` steps of 1 ms
    (``MjxSimulator.run_closed_loop``): settle, then the closed loop, chunk by chunk.

    Each world settles at ``initial_pose`` under the position servo for ``settle_steps``
    steps, as in ``MjxSimulator.run``; from t = 0 the policy maps each sample k
    (``Observation`` at t = k CONTROL_PERIOD, k = 0 .. steps) to the motor currents (n,) A of
    step k (the last sample's are not applied): torque = current / true ratio, clamped at the
    effort limit, as the CPU Simulator's CURRENT mode (the sample before a step, the command
    after it: ``control.loop.run_control`` in lock step, with ``steps`` cycles). The measured
    current is ratio x applied torque + noise; world w's noise at sample k comes from
    ``fold_in(fold_in(PRNGKey(seed), id_w), k)``, ``id_w`` = ``world_ids[w]``: with global ids
    it does not depend on how the worlds are chunked.

    A world goes to POSITION mode, holding its measured position, for the rest of the run
    (``fault_step``, ``fault_code``) when, as on the CPU Simulator and the ``Arm``, a joint
    reaches its limit, a torque exceeds the effort limit or a joint ``overspeed`` (the sample
    after the step shows the fault), or at a sample whose command is refused (NaN/inf or
    beyond ``current_limit`` A, never sent) or where the policy returns ``stop``; the policy
    state stays as after the last sample whose command was sent (``run_control``: a tripped
    sample is not counted).

    Args:
        sim: the simulator (``MjxSimulator``; this is its method ``run_closed_loop``).
        truth: the worlds' true robots (W worlds).
        policy: a ``Policy(init, step)`` of pure JAX functions of one world, vmapped over
            worlds here.
        params: the policy's parameters, a pytree of (W, ...) arrays.
        state: the initial policy state, a pytree of (W, ...) arrays, or None when
            ``policy.init`` makes it from sample 0.
        steps: steps of the closed loop (>= 1).
        reference: (steps + 1, m), shared by the worlds: row k goes to the policy with sample
            k (None: an empty row).
        pushes: forces on the end effectors (world frame).
        initial_pose: a pose name, (n,) or (W, n) rad; None: ``Robot.idle_pose``.
        settle_steps: steps of the settling before t = 0 (>= 1: sample 0 is the settled state).
        seed: of the current noise.
        every: records every ``every``-th step (0: only the final state).
        progress: ``progress(steps_done, steps_total)`` after each chunk.
        world_ids: (W,) ints >= 0, the worlds' ids of the noise (default 0 .. W - 1).

    Returns:
        The ``ClosedLoopResult``.

    Raises:
        InputError: an argument out of its range, shape or kind.
    """
    steps, settle_steps, every = _checked_counts(steps, settle_steps, every, policy, state)
    w = truth.worlds
    ref = _checked_reference(reference, steps)
    if pushes is None:
        pushes = PushSchedule(np.zeros((w, 1)), np.ones((w, 1)), np.zeros((w, 1, 3)))
    pushes = pushes.checked(w)
    params = _per_world(params, w, "params")
    clock = sim.run_clock()
    loop = _prepare(sim, truth, policy, params, state, ref, pushes, initial_pose, seed, world_ids)
    chunk = _chunk(sim, len(loop.q0), every, max(steps, settle_steps))
    loop = _compile(sim, loop, policy, every, chunk, ref)
    clock.mark()
    carry = _settle(loop, ref, settle_steps)
    q_start = np.asarray(carry[0])[:w].astype(float)
    clock.mark()
    carry, out = _close_loop(sim, loop, ref, carry, w, every, progress)
    final = jax.tree_util.tree_map(lambda a: np.asarray(a)[:w], carry)
    clock.finish()
    n_rec = -(-steps // every) if every else 0
    return ClosedLoopResult(
        (np.arange(n_rec) * every + 1) * CONTROL_PERIOD if every else np.zeros(0),
        *(out.get(k) for k in _RECORDED),
        state=final[5],
        q_start=q_start,
        fault_step=final[7].astype(int),
        fault_code=final[8].astype(int),
        every=every,
    )


#: What the closed loop records of each step (``ClosedLoopResult``).
_RECORDED = ("q", "dq", "current", "command")


class _Loop(NamedTuple):
    """A closed-loop run's compiled chunk function and its inputs (Wp worlds, padded)."""

    fn: Callable | None
    fields: dict  # per world, placed on the device(s)
    params: PyTree  # per world, placed
    carry: tuple  # the initial carry, placed
    q0: np.ndarray  # (Wp, n) rad, the initial poses
    chunk: int
    put: Callable
    put_shared: Callable


def _checked_counts(
    steps: int, settle_steps: int, every: int, policy: Policy, state: PyTree | None
) -> tuple[int, int, int]:
    """The step counts as ints, the policy and its initial state checked (InputError)."""
    steps, settle_steps, every = int(steps), int(settle_steps), int(every)
    if steps < 1:
        raise InputError(f"steps must be >= 1, got {steps}")
    if settle_steps < 1:
        raise InputError("settle_steps must be >= 1: sample 0 is the settled state")
    if every < 0:
        raise InputError(f"every must be >= 0 (0: no recording), got {every}")
    if not (
        isinstance(policy, Policy)
        and callable(policy.step)
        and (policy.init is None or callable(policy.init))
    ):
        raise InputError(
            "policy must be a function pair Policy(init, step) (init may be None), got "
            f"{type(policy).__name__}"
        )
    if (policy.init is None) == (state is None):
        raise InputError(
            "give the initial policy state either as state or as policy.init, not both"
            if state is not None
            else "policy.init is None: give the initial policy state (state)"
        )
    return steps, settle_steps, every


def _checked_reference(reference: np.ndarray | None, steps: int) -> np.ndarray:
    """The reference (steps + 1, m), finite (an empty row per sample without one)."""
    ref = np.zeros((steps + 1, 0)) if reference is None else np.asarray(reference, float)
    if ref.ndim != 2 or ref.shape[0] != steps + 1 or not np.isfinite(ref).all():
        raise InputError(
            f"reference must be a finite (steps + 1 = {steps + 1}, m) array, got shape {ref.shape}"
        )
    return ref


def _prepare(
    sim: MjxSimulator,
    truth: BatchTruth,
    policy: Policy,
    params: PyTree,
    state: PyTree | None,
    ref: np.ndarray,
    pushes: PushSchedule,
    initial_pose: str | Sequence[float] | np.ndarray | None,
    seed: int,
    world_ids: Sequence[int] | np.ndarray | None,
) -> _Loop:
    """The worlds' fields, params, poses and initial policy state, padded (not yet placed)."""
    w, n, dtype = truth.worlds, sim.n, sim.dtype
    q0 = sim.initial_poses(initial_pose, w)
    fields = sim.world_fields(truth)
    fields.update(
        push_start=pushes.start.astype(dtype),
        push_duration=pushes.duration.astype(dtype),
        push_force=pushes.force.astype(dtype),
        key=sim.world_keys(seed, _world_ids(world_ids, w)),
    )
    pad = world_padding(sim.mesh, w)
    wp = len(pad)
    padded = lambda tree: jax.tree_util.tree_map(lambda a: a[pad], tree)  # noqa: E731
    fields, params, q0 = padded(fields), padded(params), q0[pad].astype(dtype)
    zeros = np.zeros((wp, n), dtype)
    if policy.init is None:
        pstate = padded(_per_world(state, w, "state"))
    else:  # zeros of init's structure until sample 0 replaces them
        obs = Observation(np.zeros(wp), zeros, zeros, zeros, np.zeros((wp, ref.shape[1])))
        with sim.precision():
            shapes = jax.eval_shape(jax.vmap(policy.init), params, obs)
        pstate = jax.tree_util.tree_map(lambda sd: np.zeros(sd.shape, sd.dtype), shapes)
    carry = (q0, zeros, zeros, np.zeros((wp, 3), dtype), zeros, pstate, q0)
    put, put_shared = placement(sim.mesh)
    return _Loop(None, fields, params, carry, q0, 0, put, put_shared)


def _chunk(sim: MjxSimulator, wp: int, every: int, steps: int) -> int:
    """Steps per compiled call: as ``MjxSimulator.chunk_length`` when recording, else
    ``chunk_steps`` (default 100 on the CPU, else 1000), at most ``steps``."""
    if every:
        return sim.chunk_length(wp, every, steps)
    chunk = sim.chunk_steps or (100 if sim.backend == "cpu" else 1000)
    return min(int(chunk), steps)


def _compile(
    sim: MjxSimulator, loop: _Loop, policy: Policy, every: int, chunk: int, ref: np.ndarray
) -> _Loop:
    """The loop's inputs placed on the device(s) and its compiled chunk function of ``chunk``
    steps."""
    put, wp = loop.put, len(loop.q0)
    fields, params = put(loop.fields), put(loop.params)
    no_fault = np.full(wp, -1, np.int32)
    carry = put(loop.carry + (no_fault, np.zeros(wp, np.int32)))
    # the compiled step sees (chunk, m) rows of the reference, never its length; the limits
    # it closes over are part of the key
    current_limit = tuple(np.asarray(sim.current_limit, float).tolist())
    key = (
        "closed",
        policy,
        chunk,
        every,
        sim.overspeed,
        current_limit,
        sim.mesh,
        _signature(fields, params, carry, ref[0]),
    )
    fn = sim.compiled_function(
        key, lambda: _build(sim, policy, every, sim.overspeed, np.array(current_limit))
    )
    return loop._replace(fn=fn, fields=fields, params=params, carry=carry, chunk=chunk)


def _rows(loop: _Loop, ref: np.ndarray, first: int) -> jax.Array:
    """The reference rows of samples first .. first + chunk - 1 (clipped to the plan), placed."""
    steps = ref.shape[0] - 1
    return loop.put_shared(ref[np.clip(np.arange(first, first + loop.chunk), 0, steps)])


def _settle(loop: _Loop, ref: np.ndarray, settle_steps: int) -> tuple:
    """The carry after the settling (steps -settle_steps .. -1, held in POSITION mode)."""
    carry, chunk = loop.carry, loop.chunk
    for s in range(-settle_steps, 0, chunk):
        carry, _, _ = loop.fn(
            loop.fields,
            loop.params,
            carry,
            _rows(loop, ref, s + 1),
            np.int32(s),
            np.int32(min(chunk, -s)),
        )
    return carry


def _close_loop(
    sim: MjxSimulator,
    loop: _Loop,
    ref: np.ndarray,
    carry: tuple,
    w: int,
    every: int,
    progress: Callable[[int, int], None] | None,
) -> tuple[tuple, dict[str, np.ndarray]]:
    """The closed loop from t = 0, chunk by chunk: the final carry and the recorded samples."""
    steps, n, chunk = ref.shape[0] - 1, sim.n, loop.chunk
    n_rec = -(-steps // every) if every else 0
    out = {k: np.zeros((w, n_rec, n), sim.dtype) for k in _RECORDED} if every else {}

    def collect(pending: tuple) -> None:
        """Copy a chunk's samples to the host and report progress."""
        s, k, rec, faulted = pending
        np.asarray(faulted)  # waits for the chunk
        if out:
            nr, first = -(-k // every), s // every
            for name, a in zip(out, rec, strict=True):
                out[name][:, first : first + nr] = np.asarray(a)[:w, :nr]
        if progress is not None:
            progress(s + k, steps)

    pending: tuple | None = None
    for s in range(0, steps, chunk):
        k = min(chunk, steps - s)
        carry, rec, faulted = loop.fn(
            loop.fields, loop.params, carry, _rows(loop, ref, s + 1), np.int32(s), np.int32(k)
        )
        if pending is not None:  # host work overlaps the chunk just dispatched
            collect(pending)
        pending = (s, k, rec, faulted)
    if pending is not None:
        collect(pending)
    return carry, out


def _build(
    sim: MjxSimulator,
    policy: Policy,
    every: int,
    overspeed: float,
    current_limit: np.ndarray,
) -> Callable:
    """The jitted chunk function of ``run``: (fields, params, carry, reference rows (chunk, m),
    first step, valid steps) -> (carry, recorded samples or None, the number of worlds in
    fault on each device (devices,)).
    Carry per world: qpos, qvel, qacc_warmstart, lever of the push (site - body COM, m, from
    the previous step's kinematics, as the CPU Simulator uses it), command, policy state, held
    position, fault step, fault code."""
    mx, d0, dtype, n = sim.mjx_model, sim.mjx_data, sim.dtype, sim.n
    lo = jnp.asarray(sim.joint_limits[:, 0], dtype)
    hi = jnp.asarray(sim.joint_limits[:, 1], dtype)
    torque_limit = jnp.asarray(sim.torque_limit, dtype)
    current_limit = jnp.asarray(current_limit, dtype)
    site, body, nbody = sim.ee_site, sim.ee_body, sim.model.nbody
    step_fn = implicitfast_step(sim.model, dtype)
    init, act = policy

    def select(cond, new, old):
        return jax.tree_util.tree_map(lambda a, b: jnp.where(cond, a, b), new, old)

    def world(f, p, carry, k, ref, valid):
        qpos, qvel, qacc, lever, cmd, state, hold, fault_step, code = carry
        run = (k >= 0) & (fault_step < 0)  # CURRENT mode (settling, k < 0: held)
        torque = cmd / f["ratio"]
        over_effort = run & jnp.any(jnp.abs(torque) > torque_limit)
        t0 = k * CONTROL_PERIOD
        on = (f["push_start"] <= t0) & (t0 < f["push_start"] + f["push_duration"])
        force = jnp.where(on[:, None], f["push_force"], 0.0).sum(axis=0)
        wrench = jnp.concatenate([force, jnp.cross(lever, force)])
        model = {key: f[key] for key in WORLD_MODEL_FIELDS if key in f}
        model["actuator_biasprm"] = jnp.where(run, 0.0, f["actuator_biasprm"])
        d = d0.replace(
            qpos=qpos,
            qvel=qvel,
            qacc_warmstart=qacc,
            ctrl=jnp.where(run, torque, f["kp"] * hold),
            xfrc_applied=jnp.zeros((nbody, 6), dtype).at[body].set(wrench),
        )
        *physics, fwd = step_fn(mx.tree_replace(model), d)
        q1, dq1, acc1, tau = (a.astype(dtype) for a in physics)
        lever1 = (fwd.site_xpos[site] - fwd.xipos[body]).astype(dtype)
        z = jax.random.normal(jax.random.fold_in(f["key"], jnp.maximum(k + 1, 0)), (n,), dtype)
        cur1 = f["ratio"] * tau + f["noise"] * z
        at_limit = jnp.any((q1 <= lo) | (q1 >= hi))
        fast = jnp.any(jnp.abs(dq1) > overspeed)
        fault = run & (at_limit | over_effort | fast)
        # the next command, from the state just measured (sample k + 1)
        obs = Observation((k + 1) * CONTROL_PERIOD, q1, dq1, cur1, ref)
        state_in = state if init is None else select(k + 1 == 0, init(p, obs), state)
        cmd1, state1, stop = act(p, state_in, obs)
        cmd1 = cmd1.astype(dtype)
        live = (k + 1 >= 0) & (fault_step < 0) & ~fault
        refused = live & ~jnp.all(jnp.abs(cmd1) <= current_limit)  # NaN fails too
        stop = live & ~refused & jnp.asarray(stop, bool)
        accept = live & ~refused & ~stop
        event = fault | refused | stop
        bits = (
            FAULT_LIMIT * (fault & at_limit)
            + FAULT_EFFORT * (fault & over_effort)
            + FAULT_OVERSPEED * (fault & fast)
            + FAULT_REFUSED * refused
            + FAULT_STOPPED * stop
        ).astype(jnp.int32)
        new = (
            q1,
            dq1,
            acc1,
            lever1,
            jnp.where(accept, cmd1, cmd),
            select(accept, state1, state_in),
            jnp.where(event, q1, hold),
            jnp.where(event, k + 1, fault_step),
            jnp.where(event, bits, code),
        )
        return select(valid, new, carry), (q1, dq1, cur1, cmd)

    vworld = over_worlds(world, sim.backend, (0, 0, 0, None, None, None))

    def chunk_fn(f, p, carry, refs, start, n_valid):
        def step(c, i, ref):
            return vworld(f, p, c, (start + i).astype(jnp.int32), ref, i < n_valid)

        carry, rec = scan_decimated(step, carry, refs, every)
        if rec is not None:
            rec = tuple(jnp.swapaxes(a, 0, 1) for a in rec)
        return carry, rec, jnp.sum(carry[7] >= 0)[None]

    # fields, params, carry, the samples and the fault counts (one per device): per world
    specs = (WORLDS, WORLDS, WORLDS, SHARED, SHARED, SHARED)
    return sim.ahead_of_time(chunk_fn, 2, specs, WORLDS)


def _per_world(tree: PyTree, worlds: int, name: str) -> PyTree:
    """``tree`` with numpy leaves, each with a leading world axis of ``worlds`` (InputError)."""
    tree = jax.tree_util.tree_map(np.asarray, tree)
    for leaf in jax.tree_util.tree_leaves(tree):
        if leaf.ndim < 1 or leaf.shape[0] != worlds:
            raise InputError(f"every array of {name} needs a leading axis of {worlds} worlds")
    return tree


def _signature(*trees: PyTree) -> tuple:
    """Structure, shapes and dtypes of pytrees (a key of compiled functions)."""
    leaves, struct = jax.tree_util.tree_flatten(trees)
    return (str(struct),) + tuple((tuple(a.shape), str(a.dtype)) for a in leaves)


def _world_ids(world_ids: Sequence[int] | np.ndarray | None, w: int) -> np.ndarray:
    """(w,) the worlds' ids of the noise (default 0 .. w - 1), checked."""
    ids = np.arange(w) if world_ids is None else np.asarray(world_ids)
    if ids.shape != (w,) or not np.issubdtype(ids.dtype, np.integer) or (ids < 0).any():
        raise InputError(f"world_ids must be ({w},) ints >= 0")
    return ids
