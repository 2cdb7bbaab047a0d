"""The d3rlpy side of tests/parity.rs: trains d3rlpy's DiscreteCQL, DiscreteBC (and DiscreteBCQ
for controlled runs) on the shots
`uavmeta dataset export --format npz --shots N --seed S` wrote (the very transitions `uavmeta
train --shots N --seed S` trained on), scores each greedy policy with the uavmeta package's exact
evaluation (the one `uavmeta train` scores its own networks with) and compares the two sides.
Run as `python parity_check.py DIR`; or in N shares side by side, `python parity_check.py DIR
--part K/N` for K = 0 .. N-1 (each trains every N-th run into DIR/runs-K.json), then `python
parity_check.py DIR` to judge them. Exits 1 when the criterion fails.

DIR/jobs.json names the tasks (the config and the task's name or lambda), the tolerance and the
runs: for each, its task, algorithm, seed, the npz export and the project's run directory (its
train.csv, whose last row is the project's return, and its `final` checkpoint, whose saved config
gives the settings d3rlpy is set to). DIR/results.json gets every return, the reference returns
(random, stalest, greedy, planner) and what failed.

The criterion, per task and algorithm: the two means over the seeds within `tolerance` of the
planner's |return| of each other, and both above the greedy heuristic's return. Besides, the
package must score the project's own first checkpoint of each task as train.csv does, so that
both sides are scored by one evaluation.

How each setting is matched, from d3rlpy 2.8.1's source:
- Network: VectorEncoderFactory(hidden_units) is Linear+ReLU per hidden layer, then a Linear head
  (DiscreteMeanQFunction, CategoricalPolicy): the project's QNetwork. Both initialise as
  torch.nn.Linear does (U(-1/sqrt(fan_in), 1/sqrt(fan_in))), from different streams.
- Observations: normalised as the project's `Transitions::new` does, f32(v) / f32(scale) with
  scale = (L-1, L-1, aoi_max, ...) (the raw env's observation_space.high); the evaluation env is
  `normalised=True`, as the project's evaluator feeds its network.
- Rewards: multiplied by learner.reward_scale in f64 and rounded to f32, as `Transitions::new`
  does (d3rlpy's MultiplyRewardScaler would multiply in f32).
- Optimiser: Adam(lr, betas (0.9, 0.999), eps 1e-8, no weight decay, no clipping) on both sides.
- DiscreteCQL is DoubleDQNImpl's TD loss (online argmax, target value, Huber with beta 1, i.e.
  0.5 d^2 below |d| = 1) plus alpha * mean(logsumexp_a Q(s, a) - Q(s, a_data)): the project's
  `learner.double_dqn = true`, `learner.huber = true`, which every CQL run here must have (checked
  in its saved config). d3rlpy adds the TD term whole where the project's eq. 8 takes half of it,
  so d3rlpy's alpha is twice the project's: the same loss up to a factor 2 on the whole, which
  Adam does not see (but through eps).
- Target network: d3rlpy copies it after the update at grad_step % interval == 0 with grad_step
  counted from 0 (after the 1st, 101st, 201st, .. steps), the project after the 100th, 200th, ..
- Minibatches: d3rlpy's ReplayBuffer draws each row uniformly with replacement, so its "epoch" is
  not a pass over the shots; the project's epoch is one (docs/MODEL.md section 5): consecutive
  slices of a reshuffled permutation. jobs.json's "sampling": "epochs", which tests/parity.rs
  sets, draws d3rlpy's minibatches the project's way; the losses, networks, optimiser and
  targets stay d3rlpy's own. The same batch size and step count: epochs x ceil(N / batch), in
  epochs of ceil(N / batch) steps.
- DiscreteBC: nll + beta * mean(log_softmax(f)^2) on both sides (torch's Categorical(logits=f)
  .logits are the normalised log-probabilities), beta = 0.5.
- DiscreteBCQ: the TD loss of DoubleDQNImpl with the bootstrap action the online network's best
  among the actions the imitator supports (G(a|s') / max G > tau, tau = learner.bcq_threshold),
  plus DiscreteBC's loss on the imitator, which shares the Q-function's encoder
  (share_encoder=True): the project's `bcq` with `learner.huber = true` (its target is double
  DQN's whatever `learner.double_dqn` says). The same factor on the whole loss: no alpha to match.
- The network scored: the project publishes an exponential moving average of its epochs' networks
  (learner.average_decay, bias-corrected: after epoch t, avg <- (1 - w) avg + w q with
  w = (1 - decay) / (1 - decay^t)); d3rlpy has no such option and publishes its last network. The
  same average is kept here of d3rlpy's networks after each of its epochs (fit's epoch_callback;
  training is untouched) and is what the criterion judges, with the project's decay (none when it
  is 0); d3rlpy's last network is scored too and printed beside it.

Options of jobs.json for controlled runs (tests/parity.rs sets "sampling" alone): "d3rlpy_alpha"
(else twice the project's alpha), "d3rlpy_settings" (learner keys for d3rlpy's side only, such as
{"epochs": 1}), "td": "project" (d3rlpy's CQL patched to the project's default TD form, eq. 7's max
over the target network and the squared error, for project runs without double_dqn and huber),
"average_decay" (the decay of d3rlpy's average instead of the project's; 0: none, the last network
judged), "sampling": "epochs" (d3rlpy's minibatches drawn as the project's: consecutive slices of a
reshuffled permutation; else d3rlpy's own), and a task's "references" (every reference return given
instead of computed). A task's "planner" gives the planner's return alone (the others are
computed): tests/parity.rs records it, the search being the slowest part of a run.
"""

import csv
import json
import logging
import math
import os
import sys
import time
import tomllib

import numpy as np
import torch

DIR = sys.argv[1]
torch.set_num_threads(1)

import d3rlpy  # noqa: E402
import structlog  # noqa: E402
import uavmeta  # noqa: E402
from uavmeta.evaluate import evaluate, references  # noqa: E402

# d3rlpy logs every fit at info level through structlog: warnings only.
structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))

with open(os.path.join(DIR, "jobs.json")) as f:
    JOBS = json.load(f)
TD = JOBS.get("td", "d3rlpy")
SETTINGS = ["epochs", "lr", "batch_size", "gamma", "target_update_every", "hidden",
            "reward_scale", "alpha", "double_dqn", "huber", "steps_per_epoch", "average_decay",
            "bcq_threshold"]


def project_run(out):
    """The project's run in `out`: its [learner] settings (from the checkpoint's saved config)
    and the return of its last train.csv row."""
    with open(os.path.join(out, "final.toml"), "rb") as f:
        learner = tomllib.load(f)["learner"]
    with open(os.path.join(out, "train.csv")) as f:
        rows = list(csv.DictReader(f))
    return learner, float(rows[-1]["return"])


def task_kwargs(task):
    """The UavEnv arguments of a task of jobs.json."""
    kwargs = {"config": task["config"], "set": task.get("set") or None}
    if task.get("name") is not None:
        kwargs["task"] = task["name"]
    else:
        kwargs["lam"] = float(task["lambda"])
    return kwargs


def env_of(task, normalised):
    return uavmeta.UavEnv(normalised=normalised, **task_kwargs(task))


def load(npz, scale, action_count, reward_scale):
    """The exported shots as d3rlpy's MDPDataset, observations and rewards as the project's
    networks read them."""
    d = np.load(npz)
    obs = d["observations"].astype(np.float32) / scale
    rewards = (d["rewards"].astype(np.float64) * reward_scale).astype(np.float32)
    return d3rlpy.dataset.MDPDataset(
        obs, d["actions"], rewards, d["terminals"], d["timeouts"], action_size=action_count
    )


def project_td_form():
    """Patches DiscreteCQL to the project's default TD form: eq. 7's max over the target network
    (DQNImpl's target instead of DoubleDQNImpl's) and the squared error (not Huber)."""
    from d3rlpy.algos.qlearning.torch import cql_impl, dqn_impl
    from d3rlpy.models.torch.q_functions import mean_q_function

    cql_impl.DiscreteCQLImpl.compute_target = dqn_impl.DQNImpl.compute_target
    mean_q_function.compute_huber_loss = lambda y, target: (target - y) ** 2


def epoch_sampling():
    """Patches d3rlpy's ReplayBuffer to draw minibatches as the project's MinibatchOrder does:
    consecutive slices of a permutation of the rows, reshuffled (numpy's stream, which
    d3rlpy.seed seeds) when fewer than a batch remain."""
    from d3rlpy.dataset import replay_buffer

    def sample(self, batch_size):
        n = self._buffer.transition_count
        if getattr(self, "_order", None) is None or self._order[1] + batch_size > n:
            self._order = [np.random.permutation(n), 0]
        perm, pos = self._order
        self._order[1] = pos + batch_size
        picked = [self._transition_picker(*self._buffer[int(i)]) for i in perm[pos:pos + batch_size]]
        return replay_buffer.TransitionMiniBatch.from_transitions(picked)

    replay_buffer.ReplayBuffer.sample_transition_batch = sample


class Average:
    """The project's learner.average_decay on d3rlpy's network: after epoch t, the published
    weights are avg <- (1 - w) avg + w q with w = (1 - decay) / (1 - decay^t) (q itself at t = 1)."""

    def __init__(self, decay, module):
        self.decay, self.module, self.epochs, self.avg = decay, module, 0, None

    def __call__(self, algo, epoch, total_step):
        params = [p.detach() for p in self.module(algo).parameters()]
        self.epochs += 1
        if self.avg is None:
            self.avg = [p.clone() for p in params]
            return
        w = (1 - self.decay) / (1 - self.decay**self.epochs)
        for a, p in zip(self.avg, params):
            a.mul_(1 - w).add_(p, alpha=w)

    def publish(self, algo):
        with torch.no_grad():
            for p, a in zip(self.module(algo).parameters(), self.avg):
                p.copy_(a)


def train(name, dataset, seed, learner):
    """d3rlpy's learner at the project's settings `learner`, trained for its gradient steps."""
    learner = {**learner, **JOBS.get("d3rlpy_settings", {})}
    d3rlpy.seed(seed)
    encoder = d3rlpy.models.VectorEncoderFactory(hidden_units=learner["hidden"])
    adam = d3rlpy.optimizers.AdamFactory(betas=(0.9, 0.999), eps=1e-8, weight_decay=0.0)
    batch = learner["batch_size"]
    common = dict(learning_rate=learner["lr"], optim_factory=adam, encoder_factory=encoder,
                  batch_size=batch)
    # The TD learners' target: gamma, one Q-function, the target network's period.
    td = dict(gamma=learner["gamma"], n_critics=1,
              target_update_interval=learner["target_update_every"])
    if name == "cql":
        config = d3rlpy.algos.DiscreteCQLConfig(
            **common, **td, alpha=JOBS.get("d3rlpy_alpha", 2.0 * learner["alpha"]))
    elif name == "bc":
        config = d3rlpy.algos.DiscreteBCConfig(**common, beta=0.5)
    elif name == "bcq":
        config = d3rlpy.algos.DiscreteBCQConfig(
            **common, **td, action_flexibility=learner["bcq_threshold"], beta=0.5,
            share_encoder=True)
    else:
        raise ValueError(f"algorithm {name!r}: expected cql, bc or bcq")
    algo = config.create(device="cpu:0")
    # The project's epochs: one pass over the N shots each (learner.steps_per_epoch = 0), so the
    # last epoch's mean losses compare with the last row of the project's train.csv.
    assert learner["steps_per_epoch"] == 0, learner
    per_epoch = math.ceil(dataset.transition_count / min(batch, dataset.transition_count))
    steps = learner["epochs"] * per_epoch
    decay = JOBS.get("average_decay", learner["average_decay"])
    # The network that acts: the Q-function of DiscreteCQL, the imitator of DiscreteBC (whose
    # impl has no public property for it in 2.8.1), both of DiscreteBCQ.
    module = {
        "cql": lambda a: a.impl.q_function,
        "bc": lambda a: a.impl._modules.imitator,
        # The Q-function and the imitator on its encoder (shared parameters are counted once).
        "bcq": lambda a: torch.nn.ModuleList([a.impl._modules.q_funcs, a.impl._modules.imitator]),
    }[name]
    average = Average(decay, module) if decay > 0 else None
    history = algo.fit(
        dataset,
        n_steps=steps,
        n_steps_per_epoch=per_epoch,
        show_progress=False,
        logger_adapter=d3rlpy.logging.NoopAdapterFactory(),
        epoch_callback=average,
    )
    losses = {k: v for k, v in history[-1][1].items() if not k.startswith("time_")}
    return algo, average, steps, losses


def compare(results, tolerance):
    """The criterion; prints the table and returns what failed."""
    failures = []
    for c in results["checkpoints"]:
        if abs(c["python"] - c["project"]) > 1e-6 * abs(c["project"]):
            failures.append(f"{c['path']}: the package scores the project's network "
                            f"{c['python']:.3f}, its train.csv {c['project']:.3f}")
    for key in TASKS:
        refs = results["references"][key]
        planner, greedy = refs["planner"], refs["greedy"]
        print(f"{key}: planner {planner:.1f}, greedy {greedy:.1f}, random {refs['random']:.1f}; "
              "gap = (uavmeta - d3rlpy) / |planner|")
        for algo in sorted({r["algo"] for r in results["runs"] if r["task"] == key}):
            runs = [r for r in results["runs"] if r["task"] == key and r["algo"] == algo]
            ours = np.array([r["project"] for r in runs])
            theirs = np.array([r["d3rlpy"] for r in runs])
            gap = (ours.mean() - theirs.mean()) / abs(planner)

            def summary(x):
                sd = x.std(ddof=1) if len(x) > 1 else 0.0
                return f"{x.mean():9.1f} (sd {sd:6.1f}, {(x.mean() - planner) / abs(planner):+.2%})"

            last = np.array([r["d3rlpy_last"] for r in runs])
            print(f"  {algo:>4}  uavmeta {summary(ours)}  d3rlpy {summary(theirs)}  "
                  f"gap {gap:+.2%} of the planner")
            if results["average_decay"] > 0:
                print(f"        d3rlpy's last network, not averaged: {summary(last)}, gap "
                      f"{(ours.mean() - last.mean()) / abs(planner):+.2%} (not judged)")
            print("        by seed (uavmeta/d3rlpy): "
                  + " ".join(f"{r['seed']}: {r['project']:.0f}/{r['d3rlpy']:.0f}" for r in runs))
            what = f"{key} {algo} over seeds {[r['seed'] for r in runs]}"
            if not abs(gap) <= tolerance:
                failures.append(f"{what}: uavmeta {ours.mean():.1f} and d3rlpy {theirs.mean():.1f} "
                                f"differ by {abs(gap):.2%} of the planner's return, more than "
                                f"{tolerance:.0%}")
            for name, mean in [("uavmeta", ours.mean()), ("d3rlpy", theirs.mean())]:
                if not mean > greedy:
                    failures.append(f"{what}: {name}'s mean {mean:.1f} is not above greedy "
                                    f"{greedy:.1f}")
    return failures


def reference_returns(task):
    """The reference returns of a task: random, stalest, greedy, and the planner's (recorded by
    the caller where it gives one: the search costs a minute or two a task)."""
    if "references" in task:
        return task["references"]
    env = env_of(task, normalised=False)
    if "planner" in task:
        refs = {name: evaluate(name, env, exact=True, trapped=False).ret.mean
                for name in ("random", "stalest", "greedy")}
        refs["planner"] = task["planner"]
    else:
        refs = {name: score.ret.mean for name, score in references(env, exact=True).items()}
    assert refs["planner"] > refs["greedy"], (task["key"], refs)
    return refs


def settings_of(run):
    """The project's run's settings, checked against the TD form d3rlpy is set to."""
    learner, project = project_run(run["out"])
    settings = {k: learner[k] for k in SETTINGS}
    if run["algo"] in ("cql", "bcq"):
        # BCQ's target is double DQN's on both sides whatever learner.double_dqn says.
        form = TD == "project"
        double = settings["double_dqn"] if run["algo"] == "cql" else not form
        assert double != form and settings["huber"] != form, (
            f"{run['out']}: double_dqn = {settings['double_dqn']}, huber = {settings['huber']}: "
            f"expected the TD form d3rlpy is set to ({TD})")
    return learner, project, settings


def d3rlpy_run(run, scales):
    """d3rlpy trained and scored at the settings of the project's run `run`: its row."""
    learner, project, _ = settings_of(run)
    env = env_of(TASKS[run["task"]], normalised=True)
    dataset = load(run["npz"], scales[run["task"]], int(env.action_space.n), learner["reward_scale"])
    t0 = time.time()
    algo, average, steps, losses = train(run["algo"], dataset, run["seed"], learner)

    def score():
        return evaluate(
            lambda obs: algo.predict(np.asarray(obs, dtype=np.float32)).astype(np.int64),
            env, exact=True, trapped=False,
        ).ret.mean

    last = score()
    if average is not None:
        average.publish(algo)
    published = score() if average is not None else last
    row = dict(run, project=project, d3rlpy=published, d3rlpy_last=last,
               shots=dataset.transition_count, steps=steps, seconds=time.time() - t0,
               losses=losses)
    print(f"{run['task']} {run['algo']} seed {run['seed']}: uavmeta {project:.1f}, d3rlpy "
          f"{published:.1f} (its last network {last:.1f}; {dataset.transition_count} shots, {steps} steps, "
          f"{row['seconds']:.1f} s; d3rlpy's last epoch: "
          + ", ".join(f"{k} {v:.4f}" for k, v in losses.items()) + ")", flush=True)
    return row


def train_part(part, parts):
    """Every `parts`-th run from `part` on, written to DIR/runs-PART.json."""
    scales = {k: env_of(t, False).observation_space.high.astype(np.float32)
              for k, t in TASKS.items()}
    rows = [d3rlpy_run(run, scales) for run in JOBS["runs"][part::parts]]
    with open(os.path.join(DIR, f"runs-{part}.json"), "w") as f:
        json.dump(rows, f)


if TD == "project":
    project_td_form()
if JOBS.get("sampling") == "epochs":
    epoch_sampling()

started = time.time()
TASKS = {t["key"]: t for t in JOBS["tasks"]}
if len(sys.argv) > 2:
    # `--part K/N`: train the K-th of N shares of the runs; a run without it compares them.
    part, parts = (int(x) for x in sys.argv[3].split("/"))
    train_part(part, parts)
    sys.exit(0)
parts = sorted(f for f in os.listdir(DIR) if f.startswith("runs-") and f.endswith(".json"))
if not parts:
    train_part(0, 1)
    parts = ["runs-0.json"]
results = {"runs": [], "checkpoints": [],
           "references": {key: reference_returns(task) for key, task in TASKS.items()}}
for name in parts:
    with open(os.path.join(DIR, name)) as f:
        results["runs"].extend(json.load(f))
assert len(results["runs"]) == len(JOBS["runs"]), (parts, len(JOBS["runs"]))
settings = [settings_of(run)[2] for run in JOBS["runs"]]
first = settings[0]
for run, s in zip(JOBS["runs"], settings):
    same = {k: v for k, v in s.items() if k not in ("double_dqn", "huber")}
    assert same == {k: first[k] for k in same}, (run["out"], s, first)
for key in TASKS:
    out = next(r["out"] for r in JOBS["runs"] if r["task"] == key)
    score = evaluate(f"q:0:{os.path.join(out, 'final')}", env_of(TASKS[key], False),
                     exact=True, trapped=False)
    results["checkpoints"].append({"task": key, "path": out, "project": project_run(out)[1],
                                   "python": score.ret.mean})
results["settings"] = first
results["average_decay"] = JOBS.get("average_decay", first["average_decay"])
results["seconds"] = time.time() - started
results["versions"] = {"d3rlpy": d3rlpy.__version__, "torch": torch.__version__,
                       "numpy": np.__version__}
failures = compare(results, JOBS["tolerance"])
results["failures"] = failures
with open(os.path.join(DIR, "results.json"), "w") as f:
    json.dump(results, f, indent=1)
for failure in failures:
    print(f"FAILED: {failure}")
trained = sum(r["seconds"] for r in results["runs"])
print(f"d3rlpy {d3rlpy.__version__}: {len(results['runs'])} runs, {trained:.0f} s of training "
      f"and scoring; "
      + ("parity holds" if not failures else f"{len(failures)} failed"))
sys.exit(1 if failures else 0)
