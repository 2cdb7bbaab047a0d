"""Every constructor argument of the envs (``UavEnv``, ``gymnasium.make``, the vector env and
``gymnasium.make_vec``, ``TaskSampler``, the SB3 adapter) and of ``evaluate``, ``references`` and
``normalised_score``, given hostile values (wrong types, negatives, zeros, sizes beyond the
machine, NaN and infinities, missing files, unknown names, bad ``set`` entries): each must raise a
Python exception (``ValueError``, ``TypeError`` or ``OSError``) whose message names the argument,
never crash or hang the interpreter, nor raise PyO3's ``PanicException`` (issue 85, point 3).

An interpreter crash is only seen from outside, so the cases run in child interpreters: one child
runs them in turn, saying which case it starts; a child that dies (or hangs past its time) charges
its crash to the case it was in, and a new child runs the cases after it. The children run with
``UAVMETA_MEMORY_BYTES`` at 1 GiB, so the sizes beyond it are refused on any machine by the memory
check of ``uavmeta_proto::resources``, and with a 4 GiB address-space limit, so that a size the
check misses fails fast (an allocation failure aborts) instead of filling the machine.
"""

import json
import os
import resource
import subprocess
import sys

import pytest

from conftest import REPO

MEMORY = 1 << 30
ADDRESS_SPACE = 4 << 30
# One child's time for every case left; a hang is charged to the case it stands in.
TIMEOUT = 120

# What the cases' code sees.
PRELUDE = """
import gymnasium, numpy as np, uavmeta
from uavmeta import UavEnv, VectorEnv, TaskSampler, evaluate, references, normalised_score
nan, inf = float("nan"), float("inf")
CONFIG = {config!r}
README = {readme!r}
PYPROJECT = {pyproject!r}
"""

CHILD = r"""
import json, sys
cases = json.load(sys.stdin)
namespace = {}
exec(cases.pop("__prelude__"), namespace)
for case, code in cases.items():
    print(json.dumps({"start": case}), flush=True)
    try:
        exec(code, dict(namespace))
        out = {"case": case, "raised": None}
    except BaseException as e:  # PyO3's PanicException is a BaseException
        out = {"case": case, "raised": type(e).__name__,
               "bases": [c.__name__ for c in type(e).__mro__], "message": str(e)}
    print(json.dumps(out), flush=True)
"""

# (case, code, what the message must hold, every one: the argument's name, and where the estimate
# of a size refuses it, the key behind it).
CASES = [
    # UavEnv and gymnasium.make: config and task.
    ("env-config-missing", "UavEnv(config='/nonexistent/uavmeta.toml')", ("config = ",)),
    ("env-config-int", "UavEnv(config=5)", ("config",)),
    ("env-config-bytes", "UavEnv(config=b'configs/default.toml')", ("config",)),
    ("env-config-directory", "UavEnv(config='/')", ("config = ",)),
    ("env-config-not-toml", "UavEnv(config=README)", ("config = ", "README.md")),
    ("env-config-not-a-config", "UavEnv(config=PYPROJECT)", ("config = ", "build-system")),
    ("env-task-unknown", "UavEnv(config=CONFIG, task='no-such-task')", ("task = ",)),
    ("env-task-int", "UavEnv(config=CONFIG, task=5)", ("task",)),
    ("env-task-and-lam", "UavEnv(config=CONFIG, task='lambda-300', lam=1.0)", ("task",)),
    ("env-task-and-rain", "UavEnv(config=CONFIG, task='lambda-300', rain=(0, 0, 1, 1))",
     ("task",)),
    # lam.
    ("env-lam-nan", "UavEnv(lam=nan)", ("lam",)),
    ("env-lam-inf", "UavEnv(lam=inf)", ("lam",)),
    ("env-lam-minus-inf", "UavEnv(lam=-inf)", ("lam",)),
    ("env-lam-negative", "UavEnv(lam=-1.0)", ("lam",)),
    ("env-lam-huge-int", "UavEnv(lam=10**400)", ("lam",)),
    ("env-lam-str", "UavEnv(lam='300')", ("lam",)),
    ("env-lam-bool", "UavEnv(lam=True)", ("lam",)),
    ("env-lam-list", "UavEnv(lam=[300.0])", ("lam",)),
    ("make-lam-nan", "gymnasium.make('uavmeta/UAV-v0', lam=nan)", ("lam",)),
    # rain and rain_moves_every.
    ("env-rain-off-grid", "UavEnv(lam=1.0, rain=(0, 0, 100, 100))", ("rain",)),
    ("env-rain-reversed", "UavEnv(lam=1.0, rain=(5, 5, 1, 1))", ("rain",)),
    ("env-rain-huge", "UavEnv(lam=1.0, rain=(0, 0, 2**40, 1))", ("rain",)),
    ("env-rain-negative", "UavEnv(lam=1.0, rain=(-1, 0, 1, 1))", ("rain",)),
    ("env-rain-three", "UavEnv(lam=1.0, rain=(1, 2, 3))", ("rain",)),
    ("env-rain-str", "UavEnv(lam=1.0, rain='0,0,1,1')", ("rain",)),
    ("env-rain-float", "UavEnv(lam=1.0, rain=(0.5, 0, 1, 1))", ("rain",)),
    ("env-rain-dict-partial", "UavEnv(lam=1.0, rain={'x0': 0})", ("rain",)),
    ("env-moves-zero", "UavEnv(lam=1.0, rain=(0, 0, 1, 1), rain_moves_every=0)",
     ("rain_moves_every",)),
    ("env-moves-negative", "UavEnv(lam=1.0, rain=(0, 0, 1, 1), rain_moves_every=-1)",
     ("rain_moves_every",)),
    ("env-moves-huge", "UavEnv(lam=1.0, rain=(0, 0, 1, 1), rain_moves_every=2**40)",
     ("rain_moves_every",)),
    ("env-moves-float", "UavEnv(lam=1.0, rain=(0, 0, 1, 1), rain_moves_every=1.5)",
     ("rain_moves_every",)),
    ("env-moves-without-rain", "UavEnv(lam=1.0, rain_moves_every=3)", ("rain_moves_every",)),
    # normalised, render_mode, tasks.
    ("env-normalised-str", "UavEnv(normalised='yes')", ("normalised",)),
    ("env-normalised-none", "UavEnv(normalised=None)", ("normalised",)),
    ("env-render-mode", "UavEnv(render_mode='human')", ("render_mode",)),
    ("env-tasks-list", "UavEnv(tasks=[1.0])", ("tasks",)),
    # world keys as keywords.
    ("env-world-unknown-key", "UavEnv(no_such_key=1)", ("no_such_key",)),
    ("env-horizon-negative", "UavEnv(horizon=-1)", ("horizon",)),
    ("env-horizon-zero", "UavEnv(horizon=0)", ("horizon",)),
    ("env-horizon-nan", "UavEnv(horizon=nan)", ("horizon",)),
    ("env-horizon-huge", "UavEnv(horizon=10**12)", ("horizon",)),
    ("env-horizon-object", "UavEnv(horizon=object())", ("horizon",)),
    ("env-grid-huge", "UavEnv(grid_cells=10**6)", ("grid_cells",)),
    ("env-grid-zero", "UavEnv(grid_cells=0)", ("grid_cells",)),
    ("env-devices-zero", "UavEnv(devices=0)", ("devices",)),
    ("env-devices-huge", "UavEnv(devices=10**6)", ("devices",)),
    ("env-aoi-max-huge", "UavEnv(aoi_max=10**9)", ("aoi_max",)),
    ("env-start-cell-off-grid", "UavEnv(start_cell=[100, 100])", ("start_cell",)),
    ("env-start-cell-str", "UavEnv(start_cell='0,0')", ("start_cell",)),
    # set.
    ("env-set-str", "UavEnv(set='world.devices=5')", ("set",)),
    ("env-set-int-entry", "UavEnv(set=[1])", ("set[0]",)),
    ("env-set-no-equals", "UavEnv(set=['world.devices'])", ("set[0]",)),
    ("env-set-bad-value", "UavEnv(set=['world.devices=abc'])", ("world.devices",)),
    ("env-set-unknown-key", "UavEnv(set=['nosuch.key=1'])", ("nosuch",)),
    ("env-set-grid-huge", "UavEnv(set=['world.grid_cells=1000000'])", ("world.grid_cells",)),
    ("env-set-horizon-nan", "UavEnv(set=['world.horizon=nan'])", ("world.horizon",)),
    ("env-set-planner-huge",
     "UavEnv(set=['planner.beam_width=1000000000'])", ("planner.beam_width",)),
    # VectorEnv and gymnasium.make_vec: num_envs.
    ("vec-num-envs-zero", "VectorEnv(0)", ("num_envs",)),
    ("vec-num-envs-negative", "VectorEnv(-1)", ("num_envs",)),
    ("vec-num-envs-1e6", "VectorEnv(10**6)", ("num_envs",)),
    ("vec-num-envs-1e12", "VectorEnv(10**12)", ("num_envs",)),
    ("vec-num-envs-2-64", "VectorEnv(2**64)", ("num_envs",)),
    ("vec-num-envs-2-70", "VectorEnv(2**70)", ("num_envs",)),
    ("vec-num-envs-float", "VectorEnv(1.5)", ("num_envs",)),
    ("vec-num-envs-str", "VectorEnv('4')", ("num_envs",)),
    ("vec-num-envs-bool", "VectorEnv(True)", ("num_envs",)),
    ("vec-num-envs-none", "VectorEnv(None)", ("num_envs",)),
    ("vec-num-envs-large-world",
     "VectorEnv(8, set=['world.grid_cells=1024', 'world.devices=16'])",
     ("num_envs = 8", "world.grid_cells = 1024")),
    ("make-vec-num-envs-1e12",
     "gymnasium.make_vec('uavmeta/UAV-v0', 10**12, vectorization_mode='vector_entry_point')",
     ("num_envs",)),
    # VectorEnv: the other arguments.
    ("vec-lam-nan", "VectorEnv(2, lam=nan)", ("lam",)),
    ("vec-config-missing", "VectorEnv(2, config='/nonexistent/uavmeta.toml')", ("config = ",)),
    ("vec-task-unknown", "VectorEnv(2, config=CONFIG, task='no-such-task')", ("task = ",)),
    ("vec-normalised-int", "VectorEnv(2, normalised=2)", ("normalised",)),
    ("vec-render-mode", "VectorEnv(2, render_mode='human')", ("render_mode",)),
    ("vec-set-bad-value", "VectorEnv(2, set=['world.horizon=-5'])", ("world.horizon",)),
    ("vec-horizon-huge", "VectorEnv(2, horizon=10**12)", ("horizon",)),
    ("vec-tasks-empty", "VectorEnv(2, tasks=[])", ("tasks",)),
    ("vec-tasks-str", "VectorEnv(2, tasks='lambda-300')", ("tasks",)),
    ("vec-tasks-nan", "VectorEnv(2, tasks=[nan])", ("tasks[0]",)),
    ("vec-tasks-unknown-name", "VectorEnv(2, config=CONFIG, tasks=['nope'])",
     ("tasks[0]", "task = ")),
    ("vec-tasks-unknown-key", "VectorEnv(2, tasks=[{'bogus': 1}])", ("tasks[0]",)),
    ("vec-tasks-task-int", "VectorEnv(2, tasks=[{'task': 5}])", ("tasks[0]",)),
    ("vec-tasks-lam-inf", "VectorEnv(2, tasks=[{'lam': inf}])", ("tasks[0]",)),
    ("vec-tasks-rain-off-grid", "VectorEnv(2, tasks=[{'lam': 1.0, 'rain': (0, 0, 99, 99)}])",
     ("tasks[0]",)),
    ("vec-tasks-layout-str", "VectorEnv(2, tasks=[{'lam': 1.0, 'layout': 'x'}])",
     ("tasks[0]['layout']",)),
    ("vec-tasks-layout-short", "VectorEnv(2, tasks=[{'lam': 1.0, 'layout': [(0, 0)]}])",
     ("tasks[0]['layout']",)),
    ("vec-tasks-layout-huge-seed", "VectorEnv(2, tasks=[{'lam': 1.0, 'layout': 2**70}])",
     ("tasks[0]['layout']",)),
    ("vec-tasks-layout-off-grid",
     "VectorEnv(2, tasks=[{'lam': 1.0, 'layout': [(100, 100)] * 10}])", ("tasks[0]['layout']",)),
    # TaskSampler, through the vector env that draws from it.
    ("sampler-neither", "TaskSampler()", ("tasks", "lam")),
    ("sampler-tasks-str", "TaskSampler('lambda-300')", ("tasks",)),
    ("sampler-tasks-empty", "VectorEnv(2, tasks=TaskSampler([]))", ("tasks",)),
    ("sampler-lam-nan", "VectorEnv(2, tasks=TaskSampler(lam=(nan, 1.0)))", ("lam",)),
    ("sampler-lam-inf", "VectorEnv(2, tasks=TaskSampler(lam=(0.0, inf)))", ("lam",)),
    ("sampler-lam-reversed", "VectorEnv(2, tasks=TaskSampler(lam=(5.0, 1.0)))", ("lam",)),
    ("sampler-lam-negative", "VectorEnv(2, tasks=TaskSampler(lam=(-1.0, 1.0)))", ("lam",)),
    ("sampler-lam-three", "TaskSampler(lam=(0.0, 1.0, 2.0))", ("lam",)),
    ("sampler-lam-str", "TaskSampler(lam='0,1')", ("lam",)),
    ("sampler-p-nan",
     "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), rain_probability=nan))",
     ("rain_probability",)),
    ("sampler-p-two",
     "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), rain_probability=2.0))",
     ("rain_probability",)),
    ("sampler-p-str", "TaskSampler(lam=(0.0, 1.0), rain_probability='x')", ("rain_probability",)),
    ("sampler-size-zero", "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), rain_size=(0, 1)))",
     ("rain_size",)),
    ("sampler-size-huge",
     "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), rain_size=(1, 10**6)))", ("rain_size",)),
    ("sampler-size-negative", "TaskSampler(lam=(0.0, 1.0), rain_size=(-1, 2))", ("rain_size",)),
    ("sampler-size-float", "TaskSampler(lam=(0.0, 1.0), rain_size=(1.5, 2))", ("rain_size",)),
    ("sampler-moves-zero",
     "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), rain_moves_every=(0,)))",
     ("rain_moves_every",)),
    ("sampler-moves-str", "TaskSampler(lam=(0.0, 1.0), rain_moves_every='x')",
     ("rain_moves_every",)),
    ("sampler-moves-empty",
     "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), rain_moves_every=()))",
     ("rain_moves_every",)),
    ("sampler-layouts-empty", "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), layouts=[]))",
     ("layouts",)),
    ("sampler-layouts-str", "TaskSampler(lam=(0.0, 1.0), layouts='x')", ("layouts",)),
    ("sampler-layouts-huge-seed", "TaskSampler(lam=(0.0, 1.0), layouts=[2**70])",
     ("layouts[0]",)),
    ("sampler-layouts-short",
     "VectorEnv(2, tasks=TaskSampler(lam=(0.0, 1.0), layouts=[[(0, 0)]]))", ("layouts[0]",)),
    # The SB3 adapter.
    ("sb3-venv-int", "import uavmeta.sb3; uavmeta.sb3.SB3VecEnv(5)", ("venv",)),
    # evaluate.
    ("eval-policy-unknown", "evaluate('nope')", ("policy",)),
    ("eval-policy-int", "evaluate(5)", ("policy",)),
    ("eval-policy-eps-nan", "evaluate('eps:nan')", ("policy",)),
    ("eval-policy-eps-two", "evaluate('eps:2')", ("policy",)),
    ("eval-policy-actions-missing", "evaluate('actions:/nonexistent/actions.txt')",
     ("policy", "actions")),
    ("eval-policy-checkpoint-missing", "evaluate('q:0.1:/nonexistent/final')",
     ("policy = ",)),
    ("eval-task-unknown", "evaluate('stalest', 'no-such-task', config=CONFIG)", ("task = ",)),
    ("eval-task-nan", "evaluate('stalest', nan)", ("lam",)),
    ("eval-task-object", "evaluate('stalest', object())", ("task",)),
    ("eval-task-dict-nan", "evaluate('stalest', {'lam': nan})", ("lam",)),
    ("eval-task-env-and-kwargs", "evaluate('stalest', UavEnv(), lam=1.0)", ("task",)),
    ("eval-exact-str", "evaluate('stalest', exact='yes')", ("exact",)),
    ("eval-episodes-zero", "evaluate('stalest', exact=False, episodes=0)", ("episodes",)),
    ("eval-episodes-negative", "evaluate('stalest', exact=False, episodes=-1)", ("episodes",)),
    ("eval-episodes-float", "evaluate('stalest', exact=False, episodes=1.5)", ("episodes",)),
    ("eval-episodes-str", "evaluate('stalest', exact=False, episodes='5')", ("episodes",)),
    ("eval-episodes-1e15", "evaluate('stalest', exact=False, episodes=10**15)", ("episodes",)),
    ("eval-episodes-2-64", "evaluate('stalest', exact=False, episodes=2**64)", ("episodes",)),
    ("eval-episodes-1e30", "evaluate('stalest', exact=False, episodes=10**30)", ("episodes",)),
    ("eval-episodes-moving-rain",
     "evaluate('stalest', dict(lam=1.0, rain=(0, 0, 1, 1), rain_moves_every=2), "
     "episodes=10**15)", ("episodes",)),
    ("eval-episodes-callable",
     "evaluate(lambda obs: np.zeros(len(obs), np.int64), exact=False, episodes=10**15)",
     ("episodes",)),
    ("eval-episodes-planner", "evaluate('planner', exact=False, episodes=10**15)",
     ("episodes",)),
    ("eval-eval-episodes-key",
     "evaluate('stalest', exact=False, set=['learner.eval_episodes=1000000000000000'])",
     ("episodes = ", "learner.eval_episodes")),
    ("eval-planner-memory",
     "evaluate('planner', set=['planner.beam_width=100000000', "
     "'planner.max_memory_mib=100000000'])", ("policy = ", "planner.beam_width")),
    ("eval-seed-negative", "evaluate('stalest', seed=-1)", ("seed",)),
    ("eval-seed-2-64", "evaluate('stalest', seed=2**64)", ("seed",)),
    ("eval-seed-nan", "evaluate('stalest', seed=nan)", ("seed",)),
    ("eval-lam-nan", "evaluate('stalest', lam=nan)", ("lam",)),
    ("eval-config-missing", "evaluate('stalest', config='/nonexistent/uavmeta.toml')",
     ("config",)),
    ("eval-horizon-huge", "evaluate('stalest', horizon=10**12)", ("horizon",)),
    ("eval-set-bad", "evaluate('stalest', set=['world.grid_cells=0'])", ("world.grid_cells",)),
    ("policies-planner-memory",
     "uavmeta.policies.planner(UavEnv(set=['planner.beam_width=100000000', "
     "'planner.max_memory_mib=100000000']))", ("policy = ", "planner.beam_width")),
    # references and normalised_score.
    ("refs-episodes-1e15", "references(exact=False, episodes=10**15)", ("episodes",)),
    ("refs-episodes-zero", "references(exact=False, episodes=0)", ("episodes",)),
    ("refs-seed-negative", "references(seed=-1)", ("seed",)),
    ("refs-exact-str", "references(exact='no')", ("exact",)),
    ("refs-task-unknown", "references('no-such-task', config=CONFIG)", ("task = ",)),
    ("score-str", "normalised_score('x')", ("score",)),
    ("score-episodes-1e15", "normalised_score(1.0, exact=False, episodes=10**15)",
     ("episodes",)),
]

# Calls that must succeed, so that a child that cannot run anything fails here too.
FINE = [
    ("fine-env", "UavEnv(lam=300.0, rain=(0, 0, 1, 1), rain_moves_every=2)"),
    ("fine-vector", "VectorEnv(4, tasks=TaskSampler(lam=(0.0, 900.0)), normalised=True)"),
    ("fine-evaluate", "evaluate('stalest', exact=False, episodes=3, seed=1)"),
    # An exact evaluation of a world whose rain stays runs one episode per start cell, whatever
    # `episodes`: the estimate counts the worlds it builds.
    ("fine-evaluate-exact", "evaluate('stalest', episodes=10**15)"),
    # An env evaluates nothing: a large learner.eval_episodes is refused by the evaluation.
    ("fine-env-eval-episodes", "UavEnv(set=['learner.eval_episodes=1000000000000000'])"),
]


def _limit_address_space():
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def _text(out):
    if out is None:
        return ""
    return out.decode(errors="replace") if isinstance(out, bytes) else out


def run_cases(cases):
    """``{case: code}`` run in child interpreters: ``{case: result}``, where a result is the
    child's report of what the code raised, or ``{"crash": ...}`` for the case a child died or
    hung in."""
    env = dict(os.environ, UAVMETA_MEMORY_BYTES=str(MEMORY), OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1", RAYON_NUM_THREADS="1", RUST_BACKTRACE="0")
    prelude = PRELUDE.format(config=str(REPO / "configs" / "default.toml"),
                             readme=str(REPO / "README.md"),
                             pyproject=str(REPO / "python" / "pyproject.toml"))
    results, pending = {}, list(cases)
    while pending:
        payload = json.dumps({"__prelude__": prelude, **{c: cases[c] for c in pending}})
        try:
            child = subprocess.run(
                [sys.executable, "-c", CHILD], input=payload, capture_output=True, text=True,
                env=env, cwd=REPO, timeout=TIMEOUT, preexec_fn=_limit_address_space,
            )
            stdout, stderr, code = child.stdout, child.stderr, child.returncode
        except subprocess.TimeoutExpired as e:
            stdout, stderr, code = _text(e.stdout), _text(e.stderr), "a hang"
        started = None
        for line in stdout.splitlines():
            report = json.loads(line)
            if "start" in report:
                started = report["start"]
            else:
                results[report["case"]] = report
                started = None
        if code == 0 and started is None and all(c in results for c in pending):
            break
        if started is None:  # died before its first case, or after its last
            for c in pending:
                results.setdefault(c, {"crash": code, "stderr": stderr[-3000:]})
            break
        results[started] = {"crash": code, "stderr": stderr[-3000:]}
        pending = pending[pending.index(started) + 1:]
    return results


@pytest.fixture(scope="module")
def outcomes():
    cases = {case: code for case, code, _ in CASES}
    cases.update(FINE)
    return run_cases(cases)


def test_the_cases_are_distinct():
    names = [c for c, _, _ in CASES] + [c for c, _ in FINE]
    assert len(names) == len(set(names))


@pytest.mark.parametrize("case, code, names", CASES, ids=[c for c, _, _ in CASES])
def test_a_hostile_argument_raises_an_exception_naming_it(outcomes, case, code, names):
    out = outcomes[case]
    assert "crash" not in out, f"{code}: the interpreter died ({out['crash']}):\n{out['stderr']}"
    assert out["raised"] is not None, f"{code}: raised nothing"
    assert out["raised"] != "PanicException", f"{code}: a Rust panic: {out['message']}"
    assert {"ValueError", "TypeError", "OSError"} & set(out["bases"]), (
        f"{code}: raised {out['raised']}: {out['message']}"
    )
    missing = [n for n in names if n not in out["message"]]
    assert not missing, f"{code}: {out['raised']}({out['message']!r}) does not name {missing}"


@pytest.mark.parametrize("case, code", FINE, ids=[c for c, _ in FINE])
def test_a_good_argument_passes(outcomes, case, code):
    out = outcomes[case]
    assert "crash" not in out, f"{code}: the interpreter died ({out['crash']}):\n{out['stderr']}"
    assert out["raised"] is None, f"{code}: {out['raised']}: {out['message']}"
