#!/usr/bin/env bash
# The GPU figures of docs/guide/gpu.md in one go, written as one markdown file that names the device (gpu.md) in the
# output folder. Parts (about 8 minutes together on one H200):
#   profile            PPO and Dueling DQN sweeps at 1,024 and 4,096 configurations, amjax against the plain
#                      single-file reference compiled in the same process and timed in alternation, the 4,096 cases
#                      profiled (benchmarks/gpu_profile.py: device time per kernel and source line; ~4.5 minutes);
#                      records in profile.jsonl;
#   lander             the LunarLander-v3 port at 65,536 to 1,048,576 envs (benchmarks/lunar_lander_batch.py, each
#                      size in its own process); records in lander.jsonl;
#   lander-cpu-layout  the port at 65,536 envs with the CPU layout (--strategy cpu), every backend's before
#                      amjax.strategy; records in lander.jsonl too;
# and, only when GPU_PARTS names them:
#   ppo, dqn           the same sweeps, each implementation in a fresh process (python -m benchmarks.throughput, the
#                      cases of issue 58's table; ~37 s a case, ~6 minutes both);
#   demo               `python -m train demo`'s wall time (~1 minute);
#   dqn-variants       Dueling DQN at 4,096 x 2,500 (profiled) and 1,024 x 51,200 (timed), amjax with each of
#                      GPU_VARIANTS (default command-buffers,conditional-updates. command-buffers: XLA's command
#                      buffers holding loops too, so amjax's branches, loops, run on the device as the reference's
#                      conditionals do by default; the reference compiled so too. conditional-updates: the
#                      Q-learners' branches as conditionals, which copy the learning state on a GPU;
#                      benchmarks/gpu_profile.py's VARIANTS and COMPILER_VARIANTS)
#                      beside it and the reference, then 1,024 x 5,120 profiled (the learning updates' kernels);
#                      ~8 minutes; records in dqn_variants.jsonl;
#   replicate          benchmarks/replicate_time.py's projection of `amjax replicate` (GPU_REPLICATE, default
#                      LunarLander-v3's PPO and Dueling DQN; compiles dominate on a GPU: it did not finish in 170 s
#                      on an H200), each env x agent (GPU_REPLICATE_CASES of them) with its share of the part's
#                      limit (GPU_REPLICATE_S seconds, default 240); records in replicate.jsonl.
# Each part has a time limit, so a slow part costs its own rows, not the rest (the limits allow for the harness's
# extra process starts: each script's device query, and lunar_lander_batch.py's process per size); gpu.md says
# which part stopped early. The Python parts record through benchmarks/harness.py: their JSON lines (ppo.jsonl and
# dqn.jsonl from the throughput benchmark) and the markdown rendered from them (FILE.md beside FILE.jsonl) are in
# the output folder, and gpu.md includes the rendered tables; `python -m benchmarks.harness render
# OUT_DIR/FILE.jsonl` renders one again. A rerun into the same folder appends its records to the same files, and
# their tables then show every run (each names its date and commit).
#
#   bash benchmarks/gpu.sh [OUT_DIR]        # default: benchmarks/results/gpu_<date>
#   GPU_QUICK=1 bash benchmarks/gpu.sh /tmp/gpu-smoke   # tiny sizes: checks the script on a CPU in ~5 minutes
#   GPU_PARTS="ppo dqn demo" bash benchmarks/gpu.sh     # the parts named only
#   GPU_PARTS=dqn-variants bash benchmarks/gpu.sh   # the next session's DQN experiment (one call), then:
#   GPU_PARTS=replicate GPU_REPLICATE="--env LunarLander-v3 --agent dqn" GPU_REPLICATE_CASES=1 \
#       GPU_REPLICATE_S=220 bash benchmarks/gpu.sh     # one projection (a second call)
#   GPU_LIMIT_SCALE=3 GPU_QUICK=1 bash benchmarks/gpu.sh /tmp/gpu-smoke   # every time limit x3 (a busy CPU)
#
# On a machine that cannot reach the package index (jax, flax, optax, chex, pandas and pyarrow there, no gymnax),
# put the wheels of gymnax 1.0.1, gymnasium 1.3.0 and farama-notifications in .whl/ at the repository's root
# (docs/guide/gpu.md says how to download them): they are installed into a temporary folder first.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:-benchmarks/results/gpu_$(date +%Y-%m-%d)}
mkdir -p "$out"
python=${PYTHON:-python3}

if ! "$python" -c "import gymnax" 2>/dev/null; then
    if ! ls .whl/*.whl >/dev/null 2>&1; then
        echo "gymnax is not installed and .whl/ holds no wheels to install it from (see the comment above)" >&2
        exit 2
    fi
    site=$(mktemp -d)
    "$python" -m pip install -q --no-index --no-deps --no-compile --target "$site" .whl/*.whl || exit 2
    export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1

if [ -n "${GPU_QUICK:-}" ]; then
    sizes=4,8; ppo_steps=4:5120,8:5120; dqn_steps=4:2500,8:2500; big=4; small=8; long=5120
    lander="--envs 256 512 --steps 5 --burn-in 5"; lander_cpu="--envs 256 --steps 5 --burn-in 5"
    replicate="--env CartPole-v0 --agent ppo --seeds 2 --probe-steps 1024"; replicate_cases=1; dqn_steps_short=2560
else
    sizes=1024,4096; ppo_steps=1024:51200,4096:5120; dqn_steps=1024:51200,4096:2500; big=1024; small=4096; long=51200
    lander="--envs 65536 262144 1048576 --steps 25 --burn-in 100"; lander_cpu="--envs 65536 --steps 10 --burn-in 10"
    replicate="--env LunarLander-v3 --agent ppo dqn"; replicate_cases=2; dqn_steps_short=5120
fi
replicate=${GPU_REPLICATE:-$replicate}
replicate_cases=${GPU_REPLICATE_CASES:-$replicate_cases}
scale=${GPU_LIMIT_SCALE:-1}
replicate_limit=$((${GPU_REPLICATE_S:-240} * scale))

device=$("$python" -c "import jax; d = jax.devices()[0]; print(f'{d.device_kind} ({jax.default_backend()}), jax {jax.__version__}')")
{
    echo "# GPU figures: $device"
    echo
    echo "Taken $(date -u +%Y-%m-%dT%H:%MZ) at commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown) by \`bash benchmarks/gpu.sh\`; one run each."
    echo "The tables are rendered from the records beside this file (*.jsonl); each says when, where and how."
    command -v nvidia-smi >/dev/null && echo && nvidia-smi -L | sed 's/ (UUID.*//; s/^/    /'
} >"$out/gpu.md"

parts=${GPU_PARTS:-profile lander lander-cpu-layout}
part() {  # part TITLE SECONDS COMMAND...: COMMAND with a time limit (x GPU_LIMIT_SCALE), its output in $out/TITLE.log
    local title=$1 limit=$(($2 * scale))
    shift 2
    case " $parts " in *" $title "*) ;; *) return 0 ;; esac
    rm -f "$out/$title.stopped"
    echo "== $title (at most ${limit}s)"
    local start=$SECONDS
    timeout "$limit" "$@" 2>&1 | tee "$out/$title.log"
    local status=${PIPESTATUS[0]}
    echo "== $title: exit $status after $((SECONDS - start))s"
    [ "$status" = 0 ] || echo "exit $status after $((SECONDS - start)) s of at most ${limit} s" >"$out/$title.stopped"
    return 0
}

profile() {  # the four cases, one process each; the long runs timed only
    local p=("$python" benchmarks/gpu_profile.py --out "$out/profile.jsonl")
    "${p[@]}" --agent ppo --configs "$small" --steps 5120 && "${p[@]}" --agent dqn --configs "$small" --steps 2500 &&
        "${p[@]}" --agent ppo --configs "$big" --steps "$long" --no-profile &&
        "${p[@]}" --agent dqn --configs "$big" --steps "$long" --no-profile --rounds 1
}
export -f profile
export out python big small long
part profile 360 bash -c profile
dqn_variants() {  # Dueling DQN, amjax and its variants beside the reference: both sizes, then a short profile at 1,024
    local p=("$python" benchmarks/gpu_profile.py --agent dqn --variants "$variants"
        --out "$out/dqn_variants.jsonl")
    "${p[@]}" --configs "$small" --steps 2500 && "${p[@]}" --configs "$big" --steps "$long" --no-profile --rounds 1 &&
        "${p[@]}" --configs "$big" --steps "$dqn_steps_short" --rounds 1
}
export -f dqn_variants
variants=${GPU_VARIANTS:-command-buffers,conditional-updates}
export dqn_steps_short variants
part dqn-variants 480 bash -c dqn_variants
throughput=("$python" -m benchmarks.throughput --impls amjax,reference --no-sb3 --overhead "" --sizes "$sizes")
part ppo 170 "${throughput[@]}" --agents ppo --steps $ppo_steps --out "$out/ppo.jsonl" --json "$out/ppo.json"
part dqn 180 "${throughput[@]}" --agents dqn --steps $dqn_steps --out "$out/dqn.jsonl" --json "$out/dqn.json"
part lander 150 "$python" benchmarks/lunar_lander_batch.py $lander --out "$out/lander.jsonl"
part lander-cpu-layout 90 "$python" benchmarks/lunar_lander_batch.py $lander_cpu --strategy cpu \
    --out "$out/lander.jsonl"
demo_dir=$(mktemp -d)
start=$SECONDS
part demo 90 "$python" -m train demo --out "$demo_dir/demo" --no-progress
demo_s=$((SECONDS - start))
# Each env x agent its share of the part's limit, so that a slow one is recorded as timed out and the next still runs.
part replicate "${GPU_REPLICATE_S:-240}" "$python" benchmarks/replicate_time.py $replicate --out "$out/replicate.jsonl" \
    --timeout $(((replicate_limit - 20) / replicate_cases))

stopped() {  # stopped PART...: a line for each PART that did not finish (its time limit: exit 124)
    for p in "$@"; do
        [ -e "$out/$p.stopped" ] && echo && echo "The $p part stopped early ($(cat "$out/$p.stopped")); see $p.log."
    done
    return 0
}

rendered() {  # rendered HEADING FILE.md PART...: under HEADING, FILE (its headings two levels down) if one of PARTs ran
    local heading=$1 file=$2 ran=""
    shift 2
    for p in "$@"; do [ -e "$out/$p.log" ] && ran=1; done
    [ -n "$ran" ] || return 0
    echo
    echo "## $heading"
    echo
    if [ -s "$file" ]; then sed 's/^#/###/' "$file"; else echo "No table: see $(printf '%s.log ' "$@")"; fi
    stopped "$@"
}

{
    rendered "Sweeps: amjax against the plain reference, in one process (benchmarks/gpu_profile.py)" \
        "$out/profile.md" profile
    rendered "Dueling DQN variants (benchmarks/gpu_profile.py --variants $variants)" \
        "$out/dqn_variants.md" dqn-variants
    for agent in ppo dqn; do
        [ -e "$out/$agent.log" ] || continue  # a part not run
        echo
        echo "## Sweeps: $agent, each implementation in a fresh process (benchmarks/throughput; notes in $agent.md)"
        echo
        if [ -s "$out/$agent.md" ]; then
            sed -n '/^- Run:/p; /^|/p' "$out/$agent.md"
        else
            echo "$agent: no table (see $agent.log)"
        fi
        stopped "$agent"
    done
    rendered "LunarLander-v3, random actions (benchmarks/lunar_lander_batch.py)" "$out/lander.md" \
        lander lander-cpu-layout
    if [ -e "$out/demo.log" ]; then
        echo
        echo "## amjax demo"
        echo
        if [ -s "$demo_dir/demo/summary.csv" ]; then
            echo "\`python -m train demo\`: ${demo_s} s wall, start-up and compiles included."
        else
            echo "\`python -m train demo\` did not finish (see demo.log)."
        fi
    fi
    rendered "amjax replicate, projected (benchmarks/replicate_time.py $replicate)" "$out/replicate.md" replicate
} >>"$out/gpu.md"
cat "$out/gpu.md"
