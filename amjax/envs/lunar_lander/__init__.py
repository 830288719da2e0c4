"""Gymnasium's LunarLander-v3 in pure JAX (gymnax API).

Modules: ``constants`` (Gymnasium and Box2D numbers), ``collide`` (terrain, edge-polygon manifolds),
``contacts`` and ``joints`` (the constraint solves), ``world`` (``b2World::Step``), ``env`` (game logic, the
``LunarLander`` class) and ``reference`` (Gymnasium's original and the replay harness for tests and benchmarks;
needs ``box2d`` and is not imported here).

The game logic follows Gymnasium's ``gymnasium/envs/box2d/lunar_lander.py`` (v1.3.0, MIT) and
the physics is a small port of the parts of Box2D 2.3 (pybox2d 2.3.10, zlib) that the game
uses: three bodies (hull, two legs), two revolute joints with limit and motor, edge-polygon
contacts against the ten terrain edges, the sequential-impulse solver (180 velocity / 60
position iterations) and the island sleep rule. Constants cite the file they come from.

Exact (to float32 rounding; see ``docs/lunar_lander.md`` for measured differences):
terrain, observation, reward, termination and action decoding; engine impulse geometry,
wind, initial push; semi-implicit Euler with Box2D's velocity/position clamps; the revolute
joints with limit and motor, so free flight including the reset-step leg snap matches Box2D.

Same algorithm as Box2D, but not step-exact once legs touch the ground (TOI, below): contact
manifolds (``b2CollideEdgeAndPolygon`` without ghost vertices), the contact solver (friction,
2-point block solver, warm starting by contact id, position correction), Begin/End contact
events and the island sleep rule (all bodies slow for 0.5 s and positions solved).

Approximate (measured sizes in docs/lunar_lander.md):
- no time-of-impact (TOI) sub-stepping: a fast body may sink up to ``v * dt`` into the ground
  before the next step's contact pushes it out, and Begin/End contact events fire at the next
  step's collide instead of inside the TOI sub-step (a one-step lag of a leg flag or of
  game_over on fast impacts);
- hull-ground contacts are detected (game_over) but not solved: Gymnasium ends the episode on
  the hull's first contact, so only that final observation differs;
- each leg is solved against the (at most two) terrain edges under its x-range; the y=0
  bottom edge is not modelled (the terrain lies on or above it);
- contact order inside the solver, and the order of simultaneous Begin/End events of one leg,
  follow the edge index rather than Box2D's linked lists.
The random draws are explicit inputs of :func:`reset_from_draws` / :func:`step_from_draws`;
numpy's PCG64 stream itself is not reproduced, only the distributions.
"""

from amjax.envs.lunar_lander.collide import body_origins, chunk_x, terrain_from_heights
from amjax.envs.lunar_lander.constants import HELIPAD_Y, OBS_HIGH, OBS_LOW, VELOCITY_ITERATIONS, H, W
from amjax.envs.lunar_lander.env import (
    LunarLander,
    decode_action,
    heuristic_action,
    initial_state,
    observation,
    reset_from_draws,
    reward_and_termination,
    shaping,
    step_from_draws,
)
from amjax.envs.lunar_lander.state import EnvParams, EnvState, validate_params

__all__ = [
    "H",
    "HELIPAD_Y",
    "OBS_HIGH",
    "OBS_LOW",
    "VELOCITY_ITERATIONS",
    "W",
    "EnvParams",
    "EnvState",
    "LunarLander",
    "body_origins",
    "chunk_x",
    "decode_action",
    "heuristic_action",
    "initial_state",
    "observation",
    "reset_from_draws",
    "reward_and_termination",
    "shaping",
    "step_from_draws",
    "terrain_from_heights",
    "validate_params",
]
