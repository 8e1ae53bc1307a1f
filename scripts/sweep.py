"""The paper's experiment grid: task x model x seed, each cell one ``optimize.run_experiment(config)``.

Every run gets the same optimiser settings (the options below, shared with ``scripts/optimize.py``); only the task,
the contact model and the seed change. Runs go to a local process pool by default (``--workers``, each run with
``--threads`` torch threads, default 1, so the pool does not oversubscribe the cores), or to Ray with ``--ray``
(``pip install '.[ray]'``): ``ray.init()`` attaches to the cluster named by ``RAY_ADDRESS`` when it is set (and is
then given no resources: Ray refuses num_cpus against an existing cluster), else starts a local instance with
``--workers`` CPUs; each run is a ``@ray.remote(num_cpus=1)`` task. Each run writes its own folder
``<out>/<task>/<model>/seed<k>/`` (log.json, loss.png, best.gif with ``--gif``) on the machine that ran it; the
results also come back to this process, which writes ``<out>/sweep.json`` (every run's config, summary and log)
as runs finish, so an interrupted sweep keeps what it finished (``--resume`` skips the cells already in it); a run
that raises is reported and kept in ``<out>/failed.json``, and the sweep goes on. Cells no model can run are left
out of the grid (mujoco-fd with ``--mpc``). On Ray, the scripts folder travels with the job
(``runtime_env`` working_dir), so cluster nodes need cfd_torch installed but not this checkout.
``scripts/plot_results.py`` turns sweep.json into plots and the results table.

    python scripts/sweep.py --tasks Billiards Push --models cfd ipc sdrs gb --seeds 0 1 2 --iters 20 \\
        --horizon 60 --lr 0.5 --out results/sweep
    RAY_ADDRESS=auto python scripts/sweep.py --ray ...        # on a running Ray cluster
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from optimize import DEFAULTS, MODELS, TASKS, add_arguments, run_experiment  # noqa: E402


def configs(args: argparse.Namespace) -> list[dict]:
    """The grid's configs, task-major, without the cells no model can run (mujoco-fd with MPC)."""
    shared = {k: getattr(args, k) for k in DEFAULTS if k not in ("task", "model", "seed", "out")}
    return [
        {**shared, "task": t, "model": m, "seed": s, "out": str(args.out / t / m / f"seed{s}")}
        for t in args.tasks
        for m in args.models
        for s in args.seeds
        if not (m == "mujoco-fd" and args.mpc)
    ]


def run_one(config: dict) -> dict:
    """run_experiment(config), or, if it raises, {"config", "error"}: one failed cell does not stop the sweep."""
    try:
        return run_experiment(config)
    except Exception as e:  # noqa: BLE001 (a failed run is a result of the sweep)
        return {"config": config, "error": f"{type(e).__name__}: {e}"}


def _key(config: dict) -> tuple:
    return config["task"], config["model"], config["seed"]


def _run_local(todo: list[dict], workers: int):
    if workers <= 1:
        for c in todo:
            yield run_one(c)
        return
    # spawn, not fork: a forked child of a process whose torch / numba thread pools have started can hang
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = [pool.submit(run_one, c) for c in todo]
        for f in as_completed(futures):
            yield f.result()


def _run_ray(todo: list[dict], workers: int):
    import ray

    # the scripts travel with the job (working_dir), so nodes without this checkout can import them
    ray.init(
        **({} if os.environ.get("RAY_ADDRESS") else {"num_cpus": workers}),
        include_dashboard=False,
        runtime_env={"working_dir": str(Path(__file__).resolve().parent)},
    )
    script_dir = "."  # the job's working_dir: this scripts folder

    @ray.remote(num_cpus=1)
    def remote(config: dict) -> dict:
        sys.path.insert(0, script_dir)
        from sweep import run_one

        return run_one(config)

    pending = [remote.remote(c) for c in todo]
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield ray.get(done[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=Path("results/sweep"))
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="parallel runs")
    ap.add_argument("--ray", action="store_true", help="run on Ray (RAY_ADDRESS or a local instance)")
    ap.add_argument("--resume", action="store_true", help="skip the runs already in <out>/sweep.json")
    add_arguments(ap)
    ap.set_defaults(threads=1, gif=False)
    ap.add_argument("--gif", dest="gif", action="store_true", help="write each run's best.gif")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "sweep.json"
    runs = json.loads(path.read_text())["runs"] if args.resume and path.exists() else []
    done = {_key(r["config"]) for r in runs}
    todo = [c for c in configs(args) if _key(c) not in done]
    results = (_run_ray if args.ray else _run_local)(todo, args.workers)
    failed = []
    for r in tqdm(results, total=len(todo), desc="sweep"):
        c = r["config"]
        if "error" in r:
            failed.append(r)
            tqdm.write(f"{c['task']} {c['model']} seed {c['seed']}: FAILED {r['error']}")
            (args.out / "failed.json").write_text(json.dumps(failed, indent=1))
            continue
        runs.append(r)
        path.write_text(json.dumps({"runs": runs}, indent=1))
        s = r["summary"]
        end = s.get("loss_end", s.get("loss_executed"))
        start = s.get("loss_start", s.get("loss_zero_actions"))
        tqdm.write(
            f"{c['task']} {c['model']} seed {c['seed']}: loss {start:.6g} -> {end:.6g}, {s['wall_s']:.0f} s"
        )
    print(
        f"{len(runs)} runs in {path}"
        + (f"; {len(failed)} failed, in {args.out / 'failed.json'}" if failed else "")
    )


if __name__ == "__main__":
    main()
