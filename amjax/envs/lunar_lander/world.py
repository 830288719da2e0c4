"""``b2World::Step`` for the lander's island: collide, warm start, velocity and position iterations, sleep."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from amjax.batching import select_compacted
from amjax.envs.lunar_lander.collide import candidate_edges, collide_all
from amjax.envs.lunar_lander.constants import (
    ANGULAR_SLEEP_TOL,
    CONTACT_BODY_ORDER,
    DT,
    ILLEGAL_KEY,
    INV_I,
    INV_MASS,
    JOINT_ORDER,
    LIMIT_INACTIVE,
    LINEAR_SLEEP_TOL,
    LINEAR_SLOP,
    MAX_ROTATION,
    MAX_TRANSLATION,
    POSITION_ITERATIONS,
    TIME_TO_SLEEP,
    VELOCITY_ITERATIONS,
)
from amjax.envs.lunar_lander.contacts import contact_constraint, contact_position, contact_velocity
from amjax.envs.lunar_lander.fusion import materialized, vary_together
from amjax.envs.lunar_lander.joints import joint_constraint, joint_position, joint_velocity, solve_joints_exact
from amjax.envs.lunar_lander.state import EnvState

# Under vmap, the envs with a leg on the ground (and, with exact_free_flight or jump_sweeps, the envs that sweep) and
# the envs that need more than POSITION_ITERATIONS_FOR_ALL position iterations are gathered in chunks of this fraction
# of the envs (random actions touch the ground on ~5% of env-steps once episodes are at every phase).
CONTACT_CAPACITY = 1 / 16
# Position iterations every env runs before, under vmap, the unsolved ones continue as a compacted batch (each env
# runs Box2D's iterations either way).
POSITION_ITERATIONS_FOR_ALL = 4
# Runs of sweeps with one clamp pattern that `_jumped_sweeps` may take per step; where more are needed the step is
# swept instead.
JUMP_SEGMENTS = 2


def _warm_start(bv, joints, jimp, jmot, arrays, cimp, *, bodies):
    """Velocities after applying the accumulated impulses (b2ContactSolver::WarmStart, then the joints')."""
    bv = list(bv)
    for con, b, (n1, n2, t1, t2) in zip(arrays, bodies, cimp, strict=True):
        vx, vy, w = bv[b]
        for j, (nj, tj) in enumerate(((n1, t1), (n2, t2))):
            rx, ry = (con["r1x"], con["r1y"]) if j == 0 else (con["r2x"], con["r2y"])
            act = con["vcount"] > j
            pxx = jnp.where(act, nj * con["nx"] + tj * con["ny"], 0.0)
            pyy = jnp.where(act, nj * con["ny"] - tj * con["nx"], 0.0)
            vx, vy = vx + INV_MASS[b] * pxx, vy + INV_MASS[b] * pyy
            w = w + INV_I[b] * (rx * pyy - ry * pxx)
        bv[b] = (vx, vy, w)
    for k, j in enumerate(joints):
        (ix, iy, iz), mot = jimp[k], jmot[k]
        (vax, vay, wa), (vbx, vby, wb) = bv[0], bv[k + 1]
        bv[0] = (
            vax - INV_MASS[0] * ix,
            vay - INV_MASS[0] * iy,
            wa - INV_I[0] * (j["rax"] * iy - j["ray"] * ix + mot + iz),
        )
        bv[k + 1] = (
            vbx + INV_MASS[k + 1] * ix,
            vby + INV_MASS[k + 1] * iy,
            wb + INV_I[k + 1] * (j["rbx"] * iy - j["rby"] * ix + mot + iz),
        )
    return tuple(bv)


def _sweep(bv, joints, jimp, jmot, arrays, cimp, patterns=None, *, bodies):
    """One velocity iteration: the joints, then the contacts (b2Island::Solve order), each solve ``materialized``.

    Returns velocities, impulses and the joints' clamp patterns; with ``patterns`` given, the joints take those
    branches (without contacts the iteration is then affine in velocities and impulses).
    """
    bv, jimp, jmot, cimp = list(bv), list(jimp), list(jmot), list(cimp)
    seen = [None, None]
    for k in JOINT_ORDER:
        bv[0], bv[k + 1], jimp[k], jmot[k], seen[k] = materialized(
            lambda *ops, k=k: joint_velocity(*ops[:3], k, *ops[3:]),
            bv[0],
            bv[k + 1],
            joints[k],
            jimp[k],
            jmot[k],
            None if patterns is None else patterns[k],
        )
    for idx, (con, b) in enumerate(zip(arrays, bodies, strict=True)):
        bv[b], *new = materialized(
            lambda v, con, *imp, b=b: contact_velocity(v, {**con, "b": b}, *imp),
            bv[b],
            con,
            *cimp[idx],
        )
        cimp[idx] = tuple(new)
    return tuple(bv), tuple(jimp), tuple(jmot), tuple(cimp), tuple(seen)


def _gauss_seidel(bv, joints, jimp, jmot, arrays, cimp, *, bodies, iterations):
    """Box2D's velocity solve: warm start, then ``iterations`` sweeps. Returns velocities and impulses."""
    bv = _warm_start(bv, joints, jimp, jmot, arrays, cimp, bodies=bodies)

    def body(_, carry):
        bv, jimp, jmot, cimp = carry
        return _sweep(bv, joints, jimp, jmot, arrays, cimp, bodies=bodies)[:4]

    carry = vary_together((bv, tuple(jimp), tuple(jmot), tuple(cimp)))
    return jax.lax.fori_loop(0, iterations, body, carry)


def _joints_only_gauss_seidel(iterations: int) -> Callable:
    """``_gauss_seidel`` of an island whose contact constraints are all inactive (``vcount == 0``): their solves
    change nothing, so only the joints are swept; contact impulses are returned unchanged."""

    def solve(bv, joints, jimp, jmot, arrays, cimp):
        bv, jimp, jmot, _ = _gauss_seidel(bv, joints, jimp, jmot, (), (), bodies=(), iterations=iterations)
        return vary_together((bv, jimp, jmot, tuple(cimp)))

    return solve


def _same_pattern(a: Any, b: Any) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(x == y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)]))


def _jumped_sweeps(bv, joints, jimp, jmot, *, iterations, segments):
    """Box2D's velocity solve of an island without contacts, each run of sweeps that share a clamp pattern taken
    in one jump.

    With the joints' branches fixed (the motor's clamp, the limit's clamp), a sweep is an affine map of the
    accumulated impulses (the velocities are the pre-solve velocities plus the impulses' effect):
    ``lambda' = A lambda + c``. A segment takes the pattern of the sweep from where it starts, ``A`` as that
    sweep's Jacobian (forward mode over the impulses) and the powers ``M^(2^i)`` of the homogeneous map by repeated
    squaring. It then finds the last sweep that still has the pattern by binary lifting (each candidate's pattern
    checked by running the solves untouched from there; a pattern that changes once, as the reset's limit release
    does, is found exactly), jumps there and runs that sweep. Up to ``segments`` segments cover the first
    ``iterations - 1`` sweeps; the last one runs as Box2D runs it. Returns velocities, impulses and whether the
    segments covered every sweep (where not, the caller sweeps instead).
    """
    solve = partial(_sweep, joints=joints, arrays=(), cimp=(), bodies=())

    def velocities(imp):
        return _warm_start(bv, joints, *imp, (), (), bodies=())

    def sweep(imp, patterns=None):
        v, jimp, jmot, _, seen = solve(velocities(imp), jimp=imp[0], jmot=imp[1], patterns=patterns)
        return (jimp, jmot), seen, v

    start, unravel = ravel_pytree((tuple(jimp), tuple(jmot)))
    n = start.shape[0]
    levels = max(iterations - 2, 1).bit_length()  # powers 2^0 .. 2^(levels-1) reach any run of <= iterations - 2

    def segment(carry):
        impulses, left, count = carry
        after, pattern, _ = sweep(unravel(impulses))  # its pattern, forced below, gives the same impulses

        def step(x):
            return ravel_pytree(sweep(unravel(x), pattern)[0])[0]

        after = ravel_pytree(after)[0]
        power = jnp.zeros((n + 1, n + 1), start.dtype)
        power = power.at[:n, :n].set(jax.jacfwd(step)(impulses)).at[:n, n].set(after - impulses).at[n, n].set(1)
        powers = [power]
        for _ in range(levels - 1):
            powers.append(powers[-1] @ powers[-1])
        powers = jnp.stack(powers)

        def lift(i, lifted):
            level = levels - 1 - i
            taken, offset = lifted
            candidate = powers[level] @ offset
            ok = (taken + (1 << level) < left) & _same_pattern(sweep(unravel(impulses + candidate[:n]))[1], pattern)
            return taken + jnp.where(ok, 1 << level, 0), jnp.where(ok, candidate, offset)

        offset = jnp.zeros(n + 1, start.dtype).at[n].set(1)
        taken, offset = jax.lax.fori_loop(0, levels, lift, vary_together((jnp.int32(0), offset, impulses))[:2])
        # The sweep from the last checked point still has the pattern: run it; the next one starts a new segment.
        moved = ravel_pytree(sweep(unravel(impulses + offset[:n]), pattern)[0])[0]
        return moved, left - taken - 1, count + 1

    impulses, left, _ = jax.lax.while_loop(
        lambda carry: (carry[1] > 0) & (carry[2] < segments),
        segment,
        vary_together((start, jnp.int32(iterations - 1), jnp.int32(0), bv))[:3],
    )
    (jimp, jmot), _, v = sweep(unravel(impulses))
    return (v, jimp, jmot), left == 0


def _free_flight_fixed_point(bv, joints, jimp, jmot, arrays, cimp):
    """The velocity solve of an island without contact constraints, solved exactly (``solve_joints_exact``):
    what the Gauss-Seidel sweeps converge to. Contact impulses are returned unchanged. Never needs the sweeps
    (the flag is a static ``False``)."""
    bv, jimp, jmot = solve_joints_exact(bv, joints)
    return vary_together((tuple(bv), tuple(jimp), tuple(jmot), tuple(cimp))), False


def _free_flight_jump(bv, joints, jimp, jmot, arrays, cimp, *, iterations, segments):
    """Box2D's sweeps of an island without contact constraints, jumped (``_jumped_sweeps``); also returns
    whether the jump's pattern check failed (the step must then be swept). Contact impulses are unchanged."""
    (bv, jimp, jmot), agree = _jumped_sweeps(bv, joints, jimp, jmot, iterations=iterations, segments=segments)
    return vary_together(((bv, jimp, jmot, tuple(cimp)), ~agree))


def world_step(
    state: EnvState,
    force: jax.Array,
    torque: jax.Array,
    gravity: jax.Array,
    contacts: bool = True,
    velocity_iterations: int = VELOCITY_ITERATIONS,
    exact_free_flight: bool = False,
    jump_sweeps: bool = False,
):
    """One b2World::Step(1/50, 180, 60): collide, solve the island, sleep bookkeeping.

    ``contacts=False`` (static) skips collision entirely; used for the reset step, which
    Gymnasium runs 13 m above the highest possible terrain. ``exact_free_flight`` (static) solves the
    velocities of an island without leg contacts exactly (the fixed point of the sweeps) instead of by
    ``velocity_iterations`` sweeps, which Box2D stops before they converge; ``jump_sweeps`` (static) computes
    those sweeps' result in checked jumps (``_jumped_sweeps``).
    """
    # -- b2ContactManager::Collide at the start of the step (positions of the last step).
    if contacts:
        edges = candidate_edges(state.pos)
        count, face_a, lnormal, lpoint, lpts, keys = collide_all(state.pos, state.angle, state.terrain_y, edges)
        touching = count > 0
        # Old data of the same (body, edge) pair, then warm-start impulses matched by contact id.
        same = (edges[:, :, None] == state.contact_edge[:, None, :]) & (edges[:, :, None] >= 0)
        old_keys = jnp.where(same[..., None], state.contact_key[:, None], ILLEGAL_KEY)
        old_ni = jnp.sum(jnp.where(same[..., None], state.normal_impulse[:, None], 0.0), axis=2)
        old_ti = jnp.sum(jnp.where(same[..., None], state.tangent_impulse[:, None], 0.0), axis=2)
        old_keys = jnp.max(old_keys, axis=2)
        match = (keys[..., :, None] == old_keys[..., None, :]) & (keys[..., :, None] != ILLEGAL_KEY)
        first_match = match & (jnp.cumsum(match, axis=-1) == 1)
        ni0 = jnp.sum(jnp.where(first_match, old_ni[..., None, :], 0.0), axis=-1)
        ti0 = jnp.sum(jnp.where(first_match, old_ti[..., None, :], 0.0), axis=-1)
        valid = jnp.arange(2) < count[..., None]
        ni0, ti0 = jnp.where(valid, ni0, 0.0), jnp.where(valid, ti0, 0.0)
        # Begin/End contact events per (body, edge) pair.
        was = jnp.any(same & state.touching[:, None, :], axis=2)
        still = jnp.any((state.contact_edge[:, :, None] == edges[:, None, :]) & touching[:, None, :], axis=2)
        began = touching & ~was
        ended = state.touching & ~still
        game_over = state.game_over | began[0].any()
        leg_begin, leg_end = began[1:].any(axis=1), ended[1:].any(axis=1)
        leg_contact = (state.leg_contact | leg_begin) & ~leg_end
    else:
        edges, touching, keys = state.contact_edge, state.touching, state.contact_key
        ni0, ti0 = state.normal_impulse, state.tangent_impulse
        game_over, leg_contact = state.game_over, state.leg_contact

    # -- Integrate velocities (b2Island::Solve).
    h = DT
    vel = state.vel + h * (jnp.stack([0.0, gravity]) + INV_MASS[:, None] * force)
    omega = state.omega + h * INV_I * torque
    c = [(state.pos[b, 0], state.pos[b, 1]) for b in range(3)]
    a = [state.angle[b] for b in range(3)]
    bv = [(vel[b, 0], vel[b, 1], omega[b]) for b in range(3)]

    # -- Contact constraints of the legs' two candidate edges, and the joints' constraints.
    cons = []
    for b in CONTACT_BODY_ORDER if contacts else ():
        for e_idx in range(2):
            con = contact_constraint(
                b,
                count[b, e_idx],
                face_a[b, e_idx],
                lnormal[b, e_idx],
                lpoint[b, e_idx],
                lpts[b, e_idx],
                c[b],
                a[b],
            )
            cons.append((con, e_idx, True))
    joints = [joint_constraint(a[0], a[k + 1], k, state.limit_state[k]) for k in range(2)]
    cimp = [(ni0[con["b"], e, 0], ni0[con["b"], e, 1], ti0[con["b"], e, 0], ti0[con["b"], e, 1]) for con, e, _ in cons]
    jimp = [
        (
            state.joint_impulse[k, 0],
            state.joint_impulse[k, 1],
            jnp.where(j["changed"] | (j["state"] == LIMIT_INACTIVE), 0.0, state.joint_impulse[k, 2]),
        )
        for k, j in enumerate(joints)
    ]
    jmot = [state.motor_impulse[k] for k in range(2)]
    bodies = [con["b"] for con, _, _ in cons]
    arrays = [{name: value for name, value in con.items() if name != "b"} for con, _, _ in cons]
    operands = (tuple(bv), joints, tuple(jimp), tuple(jmot), arrays, tuple(cimp))
    gauss_seidel = partial(_gauss_seidel, bodies=bodies, iterations=velocity_iterations)
    # Whether a leg touches the ground: the island then holds contact constraints (vcount > 0 iff pcount > 0).
    touching_legs = jnp.any(jnp.stack([con["vcount"] > 0 for con, _, _ in cons])) if cons else False
    jump_sweeps = jump_sweeps and velocity_iterations > 2  # else nothing to jump over
    if not (exact_free_flight or jump_sweeps):
        if not cons:  # the reset step: the joints only
            bv, jimp, jmot, cimp = gauss_seidel(*operands)
        else:
            # An island without leg contacts has no contact constraints to solve (Box2D's island holds only
            # touching contacts): those steps sweep the joints alone, with the same arithmetic; the envs with a
            # leg on the ground sweep everything, gathered into a smaller batch under vmap.
            bv, jimp, jmot, cimp = select_compacted(
                touching_legs,
                gauss_seidel,
                _joints_only_gauss_seidel(velocity_iterations),
                *operands,
                capacity=CONTACT_CAPACITY,
            )
    else:
        # A step without leg contacts takes the joints' fixed point or the jumped sweeps; the rest (a leg on the
        # ground, or a clamp pattern that changed during the jump) sweep, gathered into a smaller batch under vmap.
        free_flight = (
            _free_flight_fixed_point
            if exact_free_flight
            else partial(_free_flight_jump, iterations=velocity_iterations, segments=JUMP_SEGMENTS)
        )
        out, sweep = free_flight(*operands)
        if cons:
            sweep = sweep | touching_legs
        if sweep is False:  # the exact solve of a reset step: no sweeps to compile
            bv, jimp, jmot, cimp = out
        else:
            bv, jimp, jmot, cimp = select_compacted(
                sweep,
                lambda *ops: gauss_seidel(*ops[:-1]),
                lambda *ops: ops[-1],
                *operands,
                out,
                capacity=CONTACT_CAPACITY,
            )

    # -- Store impulses per (body, edge); points beyond the solved count keep their values.
    normal_imp, tangent_imp = ni0, ti0
    for (con, e_idx, _), (n1, n2, t1, t2) in zip(cons, cimp, strict=True):
        b = con["b"]
        two = con["vcount"] == 2
        new_n = jnp.stack([n1, jnp.where(two, n2, normal_imp[b, e_idx, 1])])
        new_t = jnp.stack([t1, jnp.where(two, t2, tangent_imp[b, e_idx, 1])])
        normal_imp = normal_imp.at[b, e_idx].set(new_n)
        tangent_imp = tangent_imp.at[b, e_idx].set(new_t)

    # -- Integrate positions with the translation/rotation clamps.
    vel = jnp.stack([jnp.stack(v[:2]) for v in bv])
    omega = jnp.stack([v[2] for v in bv])
    trans2 = jnp.sum((h * vel) ** 2, axis=1)
    vel = vel * jnp.where(trans2 > MAX_TRANSLATION**2, MAX_TRANSLATION / jnp.sqrt(trans2), 1.0)[:, None]
    rot = h * omega
    omega = omega * jnp.where(rot * rot > MAX_ROTATION**2, MAX_ROTATION / jnp.abs(rot), 1.0)
    c = [(c[b][0] + h * vel[b, 0], c[b][1] + h * vel[b, 1]) for b in range(3)]
    a = [a[b] + h * omega[b] for b in range(3)]

    # -- Position iterations, stopping like Box2D once contacts and joints are within slop.
    limit_states = tuple(j["state"] for j in joints)

    def pos_iter(carry, consts, con_bodies):
        i, cs, as_, _ = carry
        con_arrays, states = consts
        cs, as_ = list(cs), list(as_)
        # Each solve materialised, as in the velocity sweeps.
        min_sep = jnp.float32(0.0)
        for con, b in zip(con_arrays, con_bodies, strict=True):
            for j in range(2):
                cx, cy, as_[b], sep = materialized(
                    lambda cx, cy, a, con, b=b, j=j: contact_position(cx, cy, a, {**con, "b": b}, j),
                    cs[b][0],
                    cs[b][1],
                    as_[b],
                    con,
                )
                cs[b] = (cx, cy)
                min_sep = jnp.minimum(min_sep, sep)
        ok = min_sep >= -3.0 * LINEAR_SLOP
        for k in JOINT_ORDER:
            cs[0], as_[0], cs[k + 1], as_[k + 1], jok = materialized(
                lambda *ops, k=k: joint_position(*ops, k), cs[0], as_[0], cs[k + 1], as_[k + 1], states[k]
            )
            ok = ok & jok
        return i + 1, tuple(cs), tuple(as_), ok

    def iterate(carry, consts, limit, con_bodies=()):
        return jax.lax.while_loop(
            lambda carry: (carry[0] < limit) & ~carry[3], lambda carry: pos_iter(carry, consts, con_bodies), carry
        )

    def joints_in_two_stages(carry, consts):
        # Most envs are solved within a few iterations; under vmap the rest continue as a smaller batch (the while
        # loop would otherwise run every env for as many iterations as the slowest one needs).
        carry = iterate(carry, consts, POSITION_ITERATIONS_FOR_ALL)
        return select_compacted(
            (carry[0] < POSITION_ITERATIONS) & ~carry[3],
            lambda carry, consts: iterate(carry, consts, POSITION_ITERATIONS),
            lambda carry, consts: carry,
            carry,
            consts,
            capacity=CONTACT_CAPACITY,
        )

    carry = vary_together((jnp.int32(0), tuple(c), tuple(a), jnp.bool_(False)))
    if contacts:
        # As in the velocity solve, an island without leg contacts corrects the joints alone (an inactive contact's
        # position solve changes nothing and reports no separation); the envs with a leg on the ground run every
        # constraint, gathered into a smaller batch under vmap.
        carry = select_compacted(
            touching_legs,
            lambda carry, consts: iterate(carry, consts, POSITION_ITERATIONS, bodies),
            lambda carry, consts: joints_in_two_stages(carry, ((), consts[1])),
            carry,
            (arrays, limit_states),
            capacity=CONTACT_CAPACITY,
        )
    else:
        # The reset step already runs on chunks of the done envs (the auto-reset's select_compacted): there the
        # loop runs plainly, which also keeps the compiled program smaller.
        carry = iterate(carry, ((), limit_states), POSITION_ITERATIONS)
    _, cs, as_, solved = carry

    # -- Sleep (b2Island::Solve with allowSleep).
    resting = (omega * omega <= ANGULAR_SLEEP_TOL**2) & (jnp.sum(vel * vel, axis=1) <= LINEAR_SLEEP_TOL**2)
    sleep_time = jnp.where(resting, state.sleep_time + h, 0.0)
    asleep = (jnp.min(sleep_time) >= TIME_TO_SLEEP) & solved
    return state.replace(
        pos=jnp.stack([jnp.stack(p) for p in cs]),
        angle=jnp.stack(as_),
        vel=vel,
        omega=omega,
        joint_impulse=jnp.stack([jnp.stack(x) for x in jimp]),
        motor_impulse=jnp.stack(jmot),
        limit_state=jnp.stack([j["state"] for j in joints]).astype(jnp.int32),
        sleep_time=sleep_time,
        contact_edge=edges,
        touching=touching,
        contact_key=keys,
        normal_impulse=normal_imp,
        tangent_impulse=tangent_imp,
        leg_contact=leg_contact,
        game_over=game_over,
        awake=~asleep,
    )
