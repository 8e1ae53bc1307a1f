"""Plots and the results table of a sweep (``scripts/sweep.py``'s ``sweep.json``).

Per task, one figure with the loss, relative to each run's start (open loop: the first iteration's loss; MPC: the
loss of zero actions), against iteration and against wall time (the time spent computing losses and gradients),
for every model: the mean over seeds and its spread (min to max), a dot at each model's total wall time; with
``--best``, open-loop runs' best loss so far instead of each iterate's. The table gives per task and model: the loss
decrease 1 - best / initial loss (open loop: the best iterate's loss, the optimiser's answer; MPC: the executed
trajectory's; mean and range over seeds), the best final distance to the goal, iterations, rollouts
(forward; ``gb``'s sampled ones included) and wall time per run, the seeds and the commits the runs were made at.
A run that ended sooner than the others of its model (an MPC episode the task ended) holds its last loss and wall
time in the mean curve.

Writes ``<out>/<task>.png`` per task and ``<out>/results.md`` (printed too); several sweep folders are merged (a
cell, task x model x seed, found in two of them is refused: the means would count it twice; so are runs of one task
and model made with different settings, whose mean would mix two experiments).

    python scripts/plot_results.py results/sweep
    python scripts/plot_results.py results/sweep/billiards results/sweep/push --out docs/experiments
    python scripts/plot_results.py results/sweep/billiards --seeds 0 1 2 --out docs/experiments/seeds012
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _cli import folder_problem, read_sweep  # noqa: E402
from _settings import DEFAULTS, MODEL_ONLY  # noqa: E402


def _curves(run: dict, best: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x iteration or control step, wall s, loss / initial loss) of one run; open loop with ``best``, the best
    loss so far (the run's answer had it stopped there)."""
    cfg, log, s = run["config"], run["log"], run["summary"]
    if cfg["mpc"]:
        x = np.array([r["step"] for r in log], dtype=float)
        # the executed and the zero-action trajectories' losses up to each step (optimize.task_loss)
        acc = {"sum": np.cumsum, "final": np.asarray, "closest": np.minimum.accumulate}[
            cfg.get("loss", "sum")
        ]
        executed = acc([r["executed_distance"] for r in log])
        zero = acc(s["zero_distances"][: len(log)])
        loss = executed / np.where(zero > 0, zero, 1.0)
    else:
        # a run stopped at a zero gradient (optimize.py's ``stopped_at``) repeats its last iterate to its budget
        log = log + [log[-1]] * (cfg["iters"] + 1 - len(log) if s.get("stopped_at") is not None else 0)
        x = np.arange(len(log), dtype=float)
        loss = np.array([r["loss"] for r in log]) / log[0]["loss"]
        if best:
            loss = np.minimum.accumulate(loss)
    return x, np.array([r["wall_s"] for r in log]), loss


def _held(values: np.ndarray, n: int) -> np.ndarray:
    """``values`` carried to length ``n`` by repeating the last."""
    return np.concatenate([values, np.full(n - len(values), values[-1])])


def _together(
    curves: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The runs' curves (:func:`_curves`) on one axis: x, the mean wall time and the losses (runs, x). A run that
    ended sooner (an MPC episode ended by the task: often the successful one) holds its last loss and wall time to
    the longest run's end, as a stopped open-loop run does."""
    n = max(len(c[0]) for c in curves)
    x = next(c[0] for c in curves if len(c[0]) == n)
    return x, np.mean([_held(c[1], n) for c in curves], 0), np.array([_held(c[2], n) for c in curves])


def _ratio(run: dict) -> float:
    s = run["summary"]
    if run["config"]["mpc"]:
        return float(_curves(run)[2][-1])
    return s.get("loss_best", s["loss_end"]) / s["loss_start"]


# settings that do not change a run's outcome (those only some models read: _settings.MODEL_ONLY)
_PER_RUN = {"seed", "out", "gif", "threads"}


def mixed_settings(runs: list[dict]) -> str | None:
    """A message if two runs of one task and model (one row of the table, one curve) were made with different
    settings (iterations, horizon, learning rate, ...: their mean would mix two experiments), else None."""
    first: dict[tuple, dict] = {}
    for r in runs:
        c = DEFAULTS | r["config"]  # keys added since a run: their defaults (as sweep.py --resume takes them)
        key = (c["task"], c["model"])
        ref = first.setdefault(key, c)
        for k in sorted((set(c) | set(ref)) - _PER_RUN):
            if MODEL_ONLY.get(k, c["model"]) != c["model"]:
                continue
            if c.get(k) != ref.get(k):
                return (
                    f"{key[0]} {key[1]}: seed {ref['seed']} and seed {c['seed']} were run with different {k} "
                    f"({ref.get(k)!r} and {c.get(k)!r}): plot them from separate folders (one row and one curve "
                    "per task and model)"
                )
    return None


def table(runs: list[dict]) -> str:
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        groups[(r["config"]["task"], r["config"]["model"])].append(r)
    lines = [
        "| task | model | loss decrease 1 - best / initial: mean (min .. max) | best final distance [m] (mean) | "
        "iterations | rollouts per run | wall s per run | seeds | commits |",
        "|---|---|---|---|---:|---:|---:|---|---|",
    ]
    for (task, model), rs in sorted(groups.items()):
        drop = 1.0 - np.array([_ratio(r) for r in rs])
        dist = np.mean(
            [r["summary"].get("best_final_distance", r["summary"].get("final_distance")) for r in rs]
        )
        cfg = rs[0]["config"]
        its = f"{cfg['iters']} x {cfg['steps']} steps" if cfg["mpc"] else str(cfg["iters"])
        if cfg["mpc"] and all("iters_run" in row for r in rs for row in r["log"]):
            # a control step at an exactly zero gradient runs none of its iterations (optimize.py)
            its += f" ({np.mean([sum(row['iters_run'] for row in r['log']) for r in rs]):.0f} run)"
        stops = [r["summary"].get("stopped_at") for r in rs]
        if any(k is not None for k in stops):
            its += (
                " (stopped at " + ", ".join("-" if k is None else str(k) for k in stops) + ": zero gradient)"
            )
        lines.append(
            f"| {task} | {model} | {drop.mean():.3g} ({drop.min():.3g} .. {drop.max():.3g}) | {dist:.4g} | "
            f"{its} | {np.mean([r['summary']['rollouts'] for r in rs]):.0f} | "
            f"{np.mean([r['summary']['wall_s'] for r in rs]):.0f} | "
            f"{' '.join(str(r['config']['seed']) for r in sorted(rs, key=lambda r: r['config']['seed']))} | "
            f"{' '.join(sorted({str(r.get('commit')) for r in rs}))} |"
        )
    return "\n".join(lines)


def plot(runs: list[dict], out: Path, best: bool = False) -> list[Path]:
    by_task: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for r in runs:
        by_task[r["config"]["task"]][r["config"]["model"]].append(r)
    paths = []
    for task, models in sorted(by_task.items()):
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
        for model, rs in sorted(models.items()):
            x, wall, L = _together([_curves(r, best) for r in rs])
            for axis, xs in ((ax[0], x), (ax[1], wall)):
                (line,) = axis.plot(xs, L.mean(0), label=f"{model} ({len(rs)} seeds)")
                axis.fill_between(xs, L.min(0), L.max(0), color=line.get_color(), alpha=0.2)
            # each model's total cost: a run stopped at its first evaluation is this point alone on the wall axis
            ax[1].plot(wall[-1:], L.mean(0)[-1:], marker="o", color=line.get_color())
        mpc = any(
            bool(r["config"]["mpc"]) for rs in models.values() for r in rs
        )  # (one kind: checked in main)
        ylabel = "best loss so far / initial" if best and not mpc else "loss / initial loss"
        ax[0].set(xlabel="control step" if mpc else "iteration", ylabel=ylabel, title=task)
        ax[1].set(xlabel="wall time [s]", ylabel=ylabel, xscale="symlog")
        ax[0].legend(fontsize=8)
        fig.tight_layout()
        path = out / f"{task}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sweeps", type=Path, nargs="+", help="folders with a sweep.json (scripts/sweep.py --out)")
    ap.add_argument("--out", type=Path, default=None, help="where to write (default: the first folder)")
    ap.add_argument(
        "--best", action="store_true", help="open loop: plot the best loss so far instead of each iterate's"
    )
    ap.add_argument(
        "--seeds", type=int, nargs="+", default=None, metavar="S",
        help="only the runs of these seeds (default: every run in the folders)",
    )  # fmt: skip
    args = ap.parse_args()
    problem = None if args.out is None else folder_problem(args.out)
    if problem:
        ap.error(f"--out {problem}")
    runs, where = [], {}
    folders = [d.resolve() for d in args.sweeps]
    if len(set(folders)) != len(folders):
        ap.error("a folder is given more than once (its runs would count twice)")
    for d in args.sweeps:
        if not (d / "sweep.json").is_file():
            ap.error(f"{d} has no sweep.json (a folder written by scripts/sweep.py --out)")
        try:
            sweep = read_sweep(d / "sweep.json")
        except ValueError as e:
            ap.error(str(e))
        for k, r in enumerate(sweep["runs"]):
            # (a run without its log or summary raised a bare KeyError or IndexError while plotting)
            log, summary = r.get("log"), r.get("summary")
            if not (isinstance(log, list) and log and all(isinstance(x, dict) for x in log)):
                ap.error(f"{d / 'sweep.json'}: run {k} has no log (a non-empty list of its iterations)")
            if not isinstance(summary, dict):
                ap.error(f"{d / 'sweep.json'}: run {k} has no summary")
            r = {**r, "config": DEFAULTS | r["config"]}  # keys added since the run: their defaults
            c = r["config"]
            if args.seeds is not None and c["seed"] not in args.seeds:
                continue
            key = (c["task"], c["model"], c["seed"])
            if key in where:
                raise SystemExit(
                    f"{key[0]} {key[1]} seed {key[2]} is in {d / 'sweep.json'} twice: pass each run once"
                    if where[key] == d
                    else f"{key[0]} {key[1]} seed {key[2]} is in both {where[key]} and {d}: pass one of them"
                )
            where[key] = d
            runs.append(r)
    if not runs:
        of = "" if args.seeds is None else f" of seeds {args.seeds}"
        raise SystemExit(f"no runs{of} in {[str(d / 'sweep.json') for d in args.sweeps]}")
    mixed = mixed_settings(runs)
    if mixed:
        raise SystemExit(mixed)
    for task in sorted({r["config"]["task"] for r in runs}):  # (before anything is written)
        if len({bool(r["config"]["mpc"]) for r in runs if r["config"]["task"] == task}) > 1:
            # control steps and iterations on one axis would mislead
            raise SystemExit(f"{task}: MPC and open-loop runs together; plot them from separate folders")
    out = args.out or args.sweeps[0]
    out.mkdir(parents=True, exist_ok=True)
    md = table(runs)
    (out / "results.md").write_text(md + "\n")
    paths = plot(runs, out, args.best)
    print(md)
    print("wrote", out / "results.md", *paths)


if __name__ == "__main__":
    main()
