"""Does PPO's critic follow the returns? One configuration's updates, probed on fresh rollouts (docs/acrobot.md,
docs/lunar_lander.md "PPO's critic").

Trains one PPO configuration with `ppo.init` / `ppo.update` and, every `--every` updates, collects a fresh rollout
of the current stochastic policy (its own key stream, apart from training's) and prints:

- `V` and `target`: the critic's mean value on the rollout and the mean GAE value target (in the reward units the
  critic learns, that is after `reward_scale`); `rel. err`: RMS(V - target) / RMS(target);
- `EV`: the explained variance 1 - Var(target - V) / Var(target) (1: the critic predicts the targets; 0: no better
  than their mean; below 0: worse);
- the mean normalised advantage (as in the loss) of the steps that measured and of those that skipped;
- `P(measure)`: the policy's mean probability of a measuring action; `H(measure)`: the mean entropy (nats) of the
  measure choice given the control drawn (0: decided; log 2 = 0.69: a coin flip);
- `return`: the mean raw / costed return of the rollout's finished episodes.

One row per arm and probe point; arms are `--arm NAME=FIELD=VALUE[,FIELD=VALUE...]` over the env's preset
(`amjax.agents.config_for`), e.g.

    python experiments/ppo_critic_probe.py --env LunarLander-v3 --cost 0.1 --seed 100 \
        --arm preset= --arm unclipped=clip_value=False --arm scaled=reward_scale=0.01
"""

from __future__ import annotations

import argparse
import ast
import time

import jax
import jax.numpy as jnp

from amjax.agents import config_for, ppo
from amjax.agents.rollout import rollout


def parse_arm(text: str) -> tuple[str, dict[str, object]]:
    """`NAME=FIELD=VALUE,FIELD=VALUE` -> (NAME, {FIELD: VALUE}); values are Python literals (else strings)."""
    name, _, rest = text.partition("=")
    fields: dict[str, object] = {}
    for item in filter(None, rest.split(",")):
        field, _, value = item.partition("=")
        try:
            fields[field] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            fields[field] = value
    return name, fields


def probe(config: ppo.PPOConfig, seed: int, every: int, updates: int) -> list[dict[str, float]]:
    """The probe's rows for `config` trained from `seed`: one at update 0, every `every` updates and at the end."""
    setup = ppo.PPO.setup(config)
    env, env_params, net = setup.env, setup.env_params, setup.network
    distribution = net.distribution
    controls = env.action_space(env_params).n // 2
    state = ppo.init(config, setup, jax.random.PRNGKey(seed))
    train_step = jax.jit(lambda s: ppo.update(config, setup, s)[0])

    @jax.jit
    def look(state, key):
        def act(batch, carry, key):
            policy, _ = net.apply(state.params, batch.obs)
            return distribution.sample(key, policy), carry, policy

        _, _, tr, logits, episodes = rollout(env, env_params, state.envs, None, act, key, config.num_steps)
        values = net.apply(state.params, tr.obs)[1]
        next_values = net.apply(state.params, tr.next_obs)[1]
        adv, targets = ppo.rollout_advantages(config, tr, values, next_values)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        measured = tr.action >= controls
        probs = jax.nn.softmax(logits)
        control = tr.action % controls
        pair = jnp.stack(
            [jnp.take_along_axis(probs, (control + k * controls)[..., None], -1)[..., 0] for k in (0, 1)], -1
        )
        p_measure_given = pair[..., 1] / pair.sum(-1)
        entropy = -(jax.scipy.special.xlogy(p_measure_given, p_measure_given)) - jax.scipy.special.xlogy(
            1 - p_measure_given, 1 - p_measure_given
        )
        finished = episodes.total().means()
        return {
            "V": values.mean(),
            "target": targets.mean(),
            "rel_err": jnp.sqrt(jnp.mean((values - targets) ** 2) / jnp.mean(targets**2)),
            "EV": 1 - jnp.var(targets - values) / jnp.var(targets),
            "adv_measured": jnp.sum(adv * measured) / jnp.maximum(measured.sum(), 1),
            "adv_skipped": jnp.sum(adv * ~measured) / jnp.maximum((~measured).sum(), 1),
            "P_measure": probs[..., controls:].sum(-1).mean(),
            "H_measure": entropy.mean(),
            "return": finished.raw_return,
            "costed": finished.costed_return,
        }

    look_key = jax.random.fold_in(jax.random.PRNGKey(seed), 0x70726F62)  # "prob": apart from training's stream
    rows = []
    for update in range(updates + 1):
        if update % every == 0 or update == updates:
            row = {k: float(v) for k, v in look(state, jax.random.fold_in(look_key, update)).items()}
            rows.append({"update": update, **row})
        if update < updates:
            state = train_step(state)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="LunarLander-v3")
    parser.add_argument("--cost", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--steps", type=int, default=1_048_576, help="the training budget (sets the schedules)")
    parser.add_argument("--updates", type=int, default=None, help="stop after this many updates (default: all)")
    parser.add_argument("--every", type=int, default=8)
    parser.add_argument("--arm", action="append", default=None, help="NAME=FIELD=VALUE[,...] (default: the preset)")
    args = parser.parse_args(argv)
    arms = [parse_arm(a) for a in args.arm or ["preset="]]
    for name, fields in arms:
        config = config_for(args.env, "ppo", cost=args.cost, total_timesteps=args.steps, **fields)
        updates = args.updates or args.steps // config.steps_per_update()
        start = time.perf_counter()
        rows = probe(config, args.seed, args.every, updates)
        seconds = time.perf_counter() - start
        print(f"\n{args.env} cost {args.cost} seed {args.seed}, arm {name} {fields} ({seconds:.0f} s)")
        print(
            "| update | V | target | rel. err | EV | adv. measured / skipped | P(measure) | H(measure) "
            "| return raw / costed |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(
                f"| {r['update']} | {r['V']:.2f} | {r['target']:.2f} | {r['rel_err']:.2f} | {r['EV']:.2f} | "
                f"{r['adv_measured']:+.3f} / {r['adv_skipped']:+.3f} | {r['P_measure']:.3f} | {r['H_measure']:.3f} | "
                f"{r['return']:.1f} / {r['costed']:.1f} |"
            )


if __name__ == "__main__":
    main()
