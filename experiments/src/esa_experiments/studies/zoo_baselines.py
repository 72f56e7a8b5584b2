"""E3 of "ESA that seeks": E2's baseline settings against RL Zoo3's tuned settings.

Rules, fixed and committed before the first run (E3 of the "ESA that seeks" round:
are the baselines E2 compares ESA with calibrated?):

* **Question.** Are E2's baselines (``seeking``'s ``ppo``, ``sac``, ``td3``: this suite's
  CPU-sized settings, ``configs/algorithms.toml``) weaker than the tuned settings of RL
  Zoo3? If so, E2 compares ESA with weak baselines, and says so.
* **Envs and budgets** as E2's: PPO on InvertedPendulum-v5, InvertedDoublePendulum-v5 and
  Hopper-v5 (30,720 / 100,352 / 100,352 steps); SAC and TD3 on InvertedDoublePendulum-v5 and
  Hopper-v5 (50,000 steps); E2's evaluation (every 2,048 or 4,096 steps on-policy, 2,500
  off-policy; 5, 3 and 3 deterministic episodes per evaluation). Quadrotor-eight is this
  suite's env and RL Zoo3 has no setting for it: it is not part of E3.
* **Arms** ``ppo_zoo``, ``sac_zoo``, ``td3_zoo``: RL Zoo3 2.9.2's hyperparameters
  (``rl_zoo3/hyperparams/{ppo,sac,td3}.yml``, held in ``configs/algorithms.toml``, checked
  against the yml by ``tests/test_zoo_baselines.py``), by env
  (:data:`esa_experiments.algorithms.ZOO_ENTRIES`):

  - PPO: the zoo's ``InvertedPendulum-v2``, ``InvertedDoublePendulum-v2`` and ``Hopper-v4``
    entries, everything as in the yml (``n_envs`` 1 included) but ``n_timesteps``: the
    budget is E2's. ``normalize: true``: training on a ``VecNormalize`` of observations and
    rewards (discounted with the entry's gamma, as the zoo does); evaluation on the same
    normalized observations with the training statistics frozen, and the env's own rewards,
    so the returns reported are the env's true returns, comparable with the other arms'
    (:mod:`esa_experiments.training`). The budgets are whole numbers of rollouts
    (``n_steps * n_envs`` = 32, 128, 512: 960, 784 and 196 rollouts). Were one not, the last
    rollout would be collected whole and the run would overshoot to the next multiple, as
    SB3's ``learn`` does for E2's ``ppo`` too (its rollouts, 1,024 and 2,048 steps, also
    divide its budgets). The InvertedPendulum and InvertedDoublePendulum entries ask for
    minibatches (64, 512) larger than their rollouts (32, 128): SB3 warns and trains on the
    whole rollout as one minibatch, as it does in the zoo.
  - SAC and TD3: the zoo's ``Hopper-v4`` entry, i.e. its ``mujoco-defaults``:
    ``learning_starts`` 10,000; TD3 also normal action noise of std 0.1, learning rate 1e-3,
    batch 256, net [400, 300], ``train_freq`` and ``gradient_steps`` 1; everything else
    SB3's defaults (SAC: learning rate 3e-4, batch 256, net [256, 256], entropy ``auto``).
    On InvertedDoublePendulum-v5 the same ``mujoco-defaults``: the zoo tunes no MuJoCo
    InvertedDoublePendulum for SAC or TD3, and these are the closest settings it has.
* **Our side**: E2's baselines ``ppo``, ``sac`` and ``td3`` with the same seeds, read from
  E2's runs (``results/seeking/runs/``: same code, settings and evaluation), not re-run. A
  run counts only when its sidecar's fingerprint is the one E2 would run now. Where E2 has
  no such run for a seed, the report says so and compares on the seeds both have.
* **Seeds** 0, 1, 2 for every zoo arm, all run, none dropped. They are E2's seeds 0-2:
  nothing of E3 is tuned on them; E3 only chooses between two fixed settings.
* **Metric** E2's: primary the AUC over the first third of the budget, secondary the
  whole-curve AUC (E2's functions: ``seeking.early``, ``verdicts.auc_by_seed``).
* **Decision**, per env, on the whole-curve AUC: the zoo's setting **beats** ours when its
  mean over the seeds exceeds ours by more than 2 standard errors of the difference (Welch:
  ``sqrt(s_zoo^2 / n + s_ours^2 / n)``, n = 3 seeds, sample standard deviations), **loses**
  when ours exceeds it by as much, else **equal**. The first third's table shows the same
  statistic and decides nothing. A family **switches** to the zoo's settings when the zoo
  beats ours on at least half of its E3 envs (PPO 2 of 3, SAC and TD3 1 of 2) and loses on
  none. Then RESULTS.md says that E2's verdict for that family is on settings the zoo beats,
  and E2's arms of that family must be rerun on the zoo's settings (a later study, not part
  of E3). Otherwise E2's settings stand. A family's decision is final once every env of it
  has the zoo's three seeds; before that the report calls it provisional.
* **Runs**: 21 (3 seeds x (3 PPO + 2 SAC + 2 TD3 envs)),
  ``python -m esa_experiments run zoo_baselines --budget full --jobs N``, then
  ``python -m esa_experiments plot zoo_baselines --budget full`` (this study's RESULTS.md
  section). The smoke budget (CI) is E2's smoke steps and evaluation with PPO rollouts of 32
  steps, compared with E2's smoke runs where they exist.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from esa_client.compare.plotting import Panel, learning_curves
from esa_client.compare.tables import summary, to_markdown
from esa_client.compare.verdicts import auc_by_seed

from esa_experiments.algorithms import LABELS
from esa_experiments.reporting import budget_table
from esa_experiments.runs import RunSpec, RunStore, atomic_write_text
from esa_experiments.studies import seeking
from esa_experiments.tasks import TASKS
from esa_experiments.training import SMOKE_BUDGET, StepBudget, rl_spec, run_training

NAME = "zoo_baselines"
DESCRIPTION = "E3: E2's baseline settings vs RL Zoo3 2.9.2's tuned settings (3 seeds)"
ENVS_OF = {
    "ppo": ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5"),
    "sac": ("InvertedDoublePendulum-v5", "Hopper-v5"),
    "td3": ("InvertedDoublePendulum-v5", "Hopper-v5"),
}
ENVS = ENVS_OF["ppo"]
ZOO_ARM = {family: f"{family}_zoo" for family in ENVS_OF}
METHODS = tuple(ZOO_ARM.values())
SEEDS = (0, 1, 2)
DEFAULT_SEEDS = "0-2"
SIGMAS = 2.0
"""The zoo beats (loses) when its mean AUC is above (below) ours by more than this many SEs."""
VERDICTS = ("**zoo beats**", "**zoo loses**", "equal")


@dataclass(frozen=True)
class Args:
    """Arguments of the study.

    Attributes:
        budgets: the zoo arms' step budget per env (E2's, the smoke budget's rollouts aside).
        ours: E2's budgets, by which E2's baseline runs are found and checked.
    """

    budgets: dict[str, StepBudget] = field(default_factory=dict)
    ours: dict[str, StepBudget] = field(default_factory=dict)


SMOKE = replace(
    SMOKE_BUDGET,
    on_policy=384,
    # The zoo's PPO has one env: 12 rollouts of 32 steps, minibatches of a rollout.
    overrides={**SMOKE_BUDGET.overrides, "ppo": {"n_steps": 32, "batch_size": 32, "n_epochs": 2}},
)

BUDGETS = {
    "smoke": Args({env: SMOKE for env in ENVS}, seeking.BUDGETS["smoke"].budgets),
    "full": Args(
        {env: seeking.BUDGETS["full"].budgets[env] for env in ENVS},
        seeking.BUDGETS["full"].budgets,
    ),
}


def specs(
    args: Args, budget: str, seeds: list[int], envs: tuple[str, ...], methods: tuple[str, ...]
) -> list[RunSpec]:
    """The zoo arms' runs, seed-major (PPO, then TD3, then SAC within a seed, as E2)."""
    return [
        rl_spec(NAME, env, ZOO_ARM[family], seed, budget, args.budgets[env])
        for seed in seeds
        for family in ("ppo", "td3", "sac")
        if ZOO_ARM[family] in methods
        for env in ENVS_OF[family]
        if env in envs
    ]


run = run_training
"""One run: train with periodic evaluation, nothing else."""


def ours(store: RunStore, args: Args) -> tuple[pd.DataFrame, list[str]]:
    """E2's baseline runs of E3's envs and seeds, and a note for each one E3 cannot use.

    A run counts when it is done under the configuration E2 would run now (its fingerprint);
    missing and stale runs are left out and named.
    """
    e2 = RunStore(seeking.NAME, store.budget, store.base)
    frames: list[pd.DataFrame] = []
    notes: list[str] = []
    for family, envs in ENVS_OF.items():
        for env in envs:
            missing: list[int] = []
            stale: list[int] = []
            for seed in SEEDS:
                spec = rl_spec(seeking.NAME, env, family, seed, store.budget, args.ours[env])
                status = e2.status(spec)
                if status == "done":
                    frame = pd.read_csv(e2.csv_path(spec))
                    frame.insert(0, "seed", seed)
                    frame.insert(0, "method", family)
                    frame.insert(0, "env", env)
                    frames.append(frame)
                else:
                    (missing if status == "todo" else stale).append(seed)
            for seeds, what in ((missing, "has no run"), (stale, "has a run of other settings")):
                if seeds:
                    notes.append(
                        f"E2's `{family}` {what} for seed(s) {seeds} on {env}: compared on the "
                        "seeds both have."
                    )
    return (pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()), notes


def decide(zoo: np.ndarray, mine: np.ndarray) -> tuple[float, float, str]:
    """The difference of the means (zoo - ours), its 2-SE bound and the verdict.

    Args:
        zoo: the zoo arm's AUCs, one per seed.
        mine: our baseline's AUCs on the same seeds.
    """
    difference = float(zoo.mean() - mine.mean())
    bound = SIGMAS * float(np.sqrt(zoo.var(ddof=1) / len(zoo) + mine.var(ddof=1) / len(mine)))
    if difference > bound:
        return difference, bound, VERDICTS[0]
    if -difference > bound:
        return difference, bound, VERDICTS[1]
    return difference, bound, VERDICTS[2]


def _mean_sd(values: np.ndarray) -> str:
    return f"{values.mean():.1f} ± {values.std(ddof=1):.1f}"


def decision_table(frame: pd.DataFrame, family: str) -> pd.DataFrame:
    """Per env of ``family``: both settings' AUC (mean ± sd over the common seeds), verdict."""
    rows = []
    for env in ENVS_OF[family]:
        zoo, mine = auc_by_seed(frame, env, ZOO_ARM[family]), auc_by_seed(frame, env, family)
        common = zoo.index.intersection(mine.index)
        if len(common) < 2:
            continue
        x, y = zoo[common].to_numpy(float), mine[common].to_numpy(float)
        difference, bound, verdict = decide(x, y)
        rows.append(
            {
                "env": env,
                "seeds": ", ".join(map(str, common)),
                "ours (E2) mean ± sd": _mean_sd(y),
                "RL Zoo3 mean ± sd": _mean_sd(x),
                "difference (zoo - ours)": f"{difference:+.1f}",
                "2 SE": f"{bound:.1f}",
                "verdict": verdict,
            }
        )
    return pd.DataFrame(rows)


def outcome(family: str, table: pd.DataFrame, zoo_seeds: dict[str, set[int]]) -> str:
    """The family's decision under the rule of the module docstring."""
    envs = ENVS_OF[family]
    verdicts = dict(zip(table.env, table.verdict, strict=True)) if not table.empty else {}
    beats = [env for env in envs if verdicts.get(env) == VERDICTS[0]]
    loses = [env for env in envs if verdicts.get(env) == VERDICTS[1]]
    complete = all(set(SEEDS) <= zoo_seeds.get(env, set()) for env in envs)
    if not verdicts:
        return f"- **{family}**: no verdict yet (no env has two seeds of both settings)."
    switch = 2 * len(beats) >= len(envs) and not loses
    state = "" if complete else " (provisional: the zoo's seeds 0-2 are not all in)"
    head = (
        f"- **{family}**{state}: the zoo beats ours on {beats or 'no env'}, loses on "
        f"{loses or 'no env'}, of {len(envs)} envs ({len(verdicts)} with a verdict)."
    )
    if switch:
        return (
            f"{head} **The family switches to the zoo's settings: E2's verdict for "
            f"{family.upper()} is on settings the zoo beats**, and E2's {family} arms must be "
            "rerun on the zoo's settings (a later study)."
        )
    return f"{head} E2's settings stand for {family.upper()}."


def report(store: RunStore, args: Args) -> str:
    """Learning curves of both settings, the decision tables and each family's outcome."""
    zoo = store.load()
    mine, notes = ours(store, args)
    frame = pd.concat([mine, zoo], ignore_index=True)
    labels = {
        **{family: f"{LABELS[family]} (ours, E2)" for family in ZOO_ARM},
        **{arm: LABELS[arm] for arm in METHODS},
    }
    panels = [
        Panel(f"{env}: {family.upper()}", env, (family, ZOO_ARM[family]))
        for family, envs in ENVS_OF.items()
        for env in envs
        if not frame[(frame.env == env) & frame.method.isin((family, ZOO_ARM[family]))].empty
    ]
    figure = learning_curves(
        frame,
        panels,
        labels,
        store.artifact("learning_curves.png"),
        suptitle="E3: our baseline settings (E2) vs RL Zoo3's tuned settings",
        ncols=4,
        per_seed=True,
    )
    thresholds = {env: TASKS[env].threshold for env in ENVS}
    table = to_markdown(summary(zoo, ENVS, METHODS, labels, thresholds, {}))
    atomic_write_text(store.artifact("table.md"), table + "\n")
    text = [f"![{NAME}]({store.relative(figure)})\n", f"RL Zoo3 arms:\n\n{table}\n"]
    lines = ["Outcome per family (decision rule in `studies/zoo_baselines.py`):", ""]
    decisions, deciding = [], []
    for family in ENVS_OF:
        whole = decision_table(frame, family)
        first = decision_table(seeking.early(frame, args.budgets), family)
        for name, part in (("whole curve, decides", whole), ("first third, shown only", first)):
            markdown = to_markdown(part) if not part.empty else "(no env has two seeds of both)"
            decisions.append(f"{family.upper()}, AUC over the {name}:\n\n{markdown}\n")
        if not whole.empty:
            deciding.append(whole.assign(family=family.upper()))
        seeds_of = {
            env: set(zoo[(zoo.env == env) & (zoo.method == ZOO_ARM[family])].seed)
            for env in ENVS_OF[family]
        }
        lines.append(outcome(family, whole, seeds_of))
    path = store.artifact("decisions.md")
    atomic_write_text(path, "\n".join(decisions))
    if deciding:
        both = pd.concat(deciding, ignore_index=True)
        both = both[["family", *(c for c in both.columns if c != "family")]]
        text.append(f"AUC over the whole curve (decides):\n\n{to_markdown(both)}\n")
    text.append(
        f"Both metrics' tables, the first third shown only: [{path.name}]"
        f"({store.relative(path)}).\n"
    )
    text.append("\n".join(lines) + "\n")
    if notes:
        text.append("E2's baseline runs E3 could not use:\n\n" + "\n".join(f"- {n}" for n in notes))
    text.append(f"\nBudgets (per run, as E2's):\n\n{budget_table(args.budgets)}\n")
    return "\n".join(text)
