"""The paper's experiment grid: task x model x seed, each cell one ``optimize.run_experiment(config)``.

Every run gets the same optimiser settings (the options below, shared with ``scripts/optimize.py``); only the task,
the contact model and the seed change. Runs go to a local process pool by default (``--workers``, each run with
``--threads`` torch threads, default 1, so the pool does not oversubscribe the cores), or to Ray with ``--ray``
(``pip install '.[ray]'``): ``ray.init()`` attaches to the cluster named by ``RAY_ADDRESS`` when it is set (and is
then given no resources: Ray refuses num_cpus against an existing cluster), else starts a local instance with
``--workers`` CPUs (``address="local"``: never a cluster ``ray start`` left running); each run is a
``@ray.remote(num_cpus=1)`` task, retried once if its worker dies (as the local pool reruns the runs of a broken
pool alone). Each run writes its own folder
``<out>/<task>/<model>/seed<k>/`` (log.json, loss.png, best.gif with ``--gif``) on the machine that ran it; the
results also come back to this process, which writes ``<out>/sweep.json`` (every run's config, summary and log)
as runs finish (through a temporary file), with each invocation's commit, host, workers and command line, so an
interrupted sweep keeps what it finished: Ctrl-C or SIGTERM ends the running runs and exits (status 130), and
``--resume`` then skips the cells already in sweep.json and refuses a cell whose settings differ from those of its
task and model's earlier runs (one row of the table, one curve: their mean would mix two experiments), telling of
runs made at another commit; an existing sweep.json is kept unless ``--resume`` or ``--overwrite`` is given, and one
sweep at a time writes to a folder (a lock). A run that raises is reported and kept, with its traceback, in
``<out>/failed.json`` (this sweep's failures; removed when none failed), and the sweep goes on (and exits with status
1 at the end). Every cell's settings are checked before any run starts. On Ray,
the scripts folder travels with the job (``runtime_env`` working_dir), so cluster nodes need cfd_torch installed
but not this checkout.
``scripts/plot_results.py`` turns sweep.json into plots and the results table.

    python scripts/sweep.py --tasks Billiards Push --models cfd ipc sdrs gb --seeds 0 1 2 --iters 20 \\
        --horizon 60 --lr 0.5 --out results/sweep
    RAY_ADDRESS=auto python scripts/sweep.py --ray ...        # on a running Ray cluster
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import multiprocessing
import os
import platform
import signal
import sys
import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cli import folder_problem, interrupted, read_sweep  # noqa: E402
from _provenance import REVISION_ENV, git_revision  # noqa: E402
from _settings import DEFAULTS, MODEL_ONLY, MODELS, unused_settings  # noqa: E402
from optimize import _check_settings, add_arguments, check_seed, run_experiment  # noqa: E402

from cfd_torch.envs import TASKS  # noqa: E402


def configs(args: argparse.Namespace) -> list[dict]:
    """The grid's configs, task-major."""
    shared = {k: getattr(args, k) for k in DEFAULTS if k not in ("task", "model", "seed", "out")}
    out = args.out.absolute()  # a run's folder whatever its working directory (Ray's is its working_dir copy)
    return [
        {**shared, "task": t, "model": m, "seed": s, "out": str(out / t / m / f"seed{s}")}
        for t in args.tasks
        for m in args.models
        for s in args.seeds
    ]


def run_one(config: dict) -> dict:
    """run_experiment(config), or, if it raises, {"config", "error", "traceback"}: one failed cell does not stop the
    sweep (an interrupt, Ctrl-C, does)."""
    try:
        return run_experiment(config)
    except Exception as e:  # noqa: BLE001 (a failed run is a result of the sweep)
        if interrupted(e):
            raise KeyboardInterrupt from e
        return {"config": config, "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}


def _key(config: dict) -> tuple:
    return config["task"], config["model"], config["seed"]


# the cell, and what a run writes where and how fast, not what it computes: free to differ on --resume
_NOT_SETTINGS = ("seed", "out", "threads", "gif")


def _settings_differ(old: dict, new: dict) -> list[str]:
    """The settings (keys of ``new`` but the output folder, threads, GIF and those the run's model does not read)
    in which an earlier run's config differs."""
    old = DEFAULTS | old  # keys added since that run: their defaults

    def same(k: str) -> bool:
        if k == "task_args":  # no task arguments, given as {} or left out, are the same run
            return (old.get(k) or None) == (new[k] or None)
        return old.get(k) == new[k]

    return [
        k
        for k in new
        if k not in _NOT_SETTINGS and MODEL_ONLY.get(k, new["model"]) == new["model"] and not same(k)
    ]


def _write(path: Path, data) -> None:
    """Write JSON through a temporary file and a rename: a sweep killed mid-write keeps the previous file."""
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def _ignore_interrupts() -> None:
    """A pool worker's initializer: Ctrl-C (SIGINT to the terminal's process group) is the sweep's to handle; a
    worker that took it would report its run as failed and start the next."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _spawn_pool(workers: int):
    """A process pool (spawn, not fork: a forked child of a process whose torch / numba thread pools have started
    can hang) that, left by an exception (an interrupt), cancels the runs not started and ends the running ones
    instead of waiting for them all."""
    pool = ProcessPoolExecutor(
        workers, mp_context=multiprocessing.get_context("spawn"), initializer=_ignore_interrupts
    )
    try:
        yield pool
    except BaseException:
        processes = pool._processes or {}  # the pool's own dict (shutdown drops the pool's reference to it)
        manager = pool._executor_manager_thread
        pool.shutdown(wait=False, cancel_futures=True)
        ended: set[int] = set()
        while live := [p for pid, p in list(processes.items()) if pid not in ended]:
            for proc in live:  # (no public way to end running tasks; the pool may start one meanwhile)
                proc.terminate()
                proc.join(10)
                ended.add(proc.pid)
        if manager is not None:  # it ends once it has seen its workers end
            manager.join(10)
        raise
    pool.shutdown(wait=True)


def _run_alone(config: dict) -> dict:
    """run_one(config) in a process of its own: a process that dies (a crash, the OOM killer) fails this run only."""
    with _spawn_pool(1) as pool:
        try:
            return pool.submit(run_one, config).result()
        except BrokenProcessPool as e:
            return {"config": config, "error": f"the run's process died: {e}"}


def _run_local(todo: list[dict], workers: int):
    if workers <= 1:
        for c in todo:
            yield run_one(c)
        return
    broken = []
    with _spawn_pool(workers) as pool:
        futures = {pool.submit(run_one, c): c for c in todo}
        for f in as_completed(futures):
            try:
                r = f.result()
            except BrokenProcessPool:  # a worker died: every unfinished run of the pool fails with it
                broken.append(futures[f])
                continue
            yield r
    # which run killed the pool is unknown: each unfinished one again, in a process of its own, one at a time (a
    # run killed for memory beside others would die again)
    for c in broken:
        yield _run_alone(c)


def _run_ray(todo: list[dict], workers: int):
    import ray

    # the scripts travel with the job (working_dir), so nodes without this checkout can import them; the copy is
    # outside any git checkout, so the runs' logs take this checkout's commit from the environment
    commit = git_revision()
    env = {REVISION_ENV: commit} if commit else {}
    # RAY_ADDRESS names a cluster to attach to (Ray refuses num_cpus against one); without it a new local
    # instance (address "local": ray.init() alone attaches to a cluster `ray start` left running)
    where = {} if os.environ.get("RAY_ADDRESS") else {"address": "local", "num_cpus": workers}
    interrupted = []
    handler = signal.signal(signal.SIGINT, lambda *_: interrupted.append(True))
    try:  # a Ctrl-C while Ray starts its processes was lost, or left some running: it ends the sweep after
        ray.init(
            **where,
            include_dashboard=False,
            runtime_env={"working_dir": str(Path(__file__).resolve().parent), "env_vars": env},
        )
    finally:
        signal.signal(signal.SIGINT, handler)
        # Ray's driver turns SIGTERM into SystemExit (and its core worker aborted on it): as Ctrl-C again
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    if interrupted:
        raise KeyboardInterrupt
    script_dir = "."  # the job's working_dir: this scripts folder

    # a run whose worker died is retried once, as the local pool retries the runs of a broken pool alone
    @ray.remote(num_cpus=1, max_retries=1)
    def remote(config: dict) -> dict:
        sys.path.insert(0, script_dir)
        from sweep import run_one

        return run_one(config)

    config_of = {}
    for c in todo:
        config_of[remote.remote(c)] = c
    pending = list(config_of)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            try:
                yield ray.get(done[0])
            except ray.exceptions.RayError as e:  # its worker died (run_one catches what the run raises)
                yield {"config": config_of[done[0]], "error": f"{type(e).__name__}: {e}"}
    finally:  # an interrupted sweep: its runs still on the cluster end with it
        for ref in pending:
            ray.cancel(ref, force=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    ap.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=Path("results/sweep"))
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    ap.add_argument(
        "--workers", type=int, default=cpus, help="parallel runs (default: the CPUs this process may use)"
    )
    ap.add_argument("--ray", action="store_true", help="run on Ray (RAY_ADDRESS or a local instance)")
    ap.add_argument(
        "--resume", action="store_true", help="skip the runs already in <out>/sweep.json, add the rest"
    )
    ap.add_argument("--overwrite", action="store_true", help="replace an existing <out>/sweep.json")
    add_arguments(ap)
    ap.set_defaults(threads=1, gif=False)
    ap.add_argument("--gif", dest="gif", action="store_true", help="write each run's best.gif")
    args = ap.parse_args()
    for name in ("tasks", "models", "seeds"):  # a cell twice would run twice into one folder
        values = getattr(args, name)
        if len(set(values)) != len(values):
            ap.error(f"--{name} lists {sorted({v for v in values if values.count(v) > 1})} more than once")
    if args.workers < 1:
        ap.error(f"--workers must be >= 1, got {args.workers}")
    problem = folder_problem(args.out)
    if problem:
        ap.error(f"--out {problem}")
    if args.ray:
        try:
            import ray  # noqa: F401
        except ImportError:
            ap.error("--ray needs Ray: pip install '.[ray]'")
    for s in args.seeds:  # (the settings' check below runs for one seed of each set of settings)
        try:
            check_seed(s)
        except ValueError as err:
            ap.error(f"argument --seeds: {err}")
    grid = configs(args)
    unused = unused_settings(grid[0] if grid else {}, sorted({c["model"] for c in grid}), not args.resume)
    if unused:
        ap.error(f"argument {unused[0]}: {unused[1]}")
    checked = set()
    for c in (
        grid
    ):  # every cell's settings checked before any runs (each task core built once per set of settings)
        key = json.dumps(
            {k: v for k, v in c.items() if k not in ("seed", "out")}, sort_keys=True, default=str
        )
        if key in checked:
            continue
        checked.add(key)
        try:
            _check_settings({**DEFAULTS, **c})
        except ValueError as err:
            ap.error(f"{c['task']} {c['model']}: {err}")
    path = args.out / "sweep.json"
    if args.resume and args.overwrite:
        ap.error("--resume and --overwrite: give one")
    if path.exists() and not (args.resume or args.overwrite):
        ap.error(f"--out: {path} exists: --resume adds to it, --overwrite replaces it")
    args.out.mkdir(parents=True, exist_ok=True)
    lock = open(args.out / ".sweep.lock", "w")  # noqa: SIM115 (held until the process ends)
    try:  # released by the system when this process ends, however it ends
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        ap.error(f"--out: another sweep is writing to {args.out}")
    try:
        old = read_sweep(path) if args.resume and path.exists() else {}
    except ValueError as e:
        ap.error(f"--resume: {e}")
    runs, sweeps = old.get("runs", []), old.get("sweeps", [])
    # --resume continues the same experiment: each task and model's runs (one row of the table, one curve of the
    # plot) share their settings; a new cell is checked against every earlier run of its task and model
    earlier = {_key(r["config"]): r["config"] for r in runs}
    for c in grid:
        for e in (e for e in earlier.values() if e["task"] == c["task"] and e["model"] == c["model"]):
            if diff := _settings_differ(e, c):
                then = DEFAULTS | e
                raise SystemExit(
                    f"--resume: {path} holds {c['task']} {c['model']} seed {e['seed']} run with other settings than "
                    f"seed {c['seed']} now ("
                    + ", ".join(f"{k}: {then.get(k)!r} there, {c[k]!r} now" for k in diff)
                    + "); resume with the same settings or write to another --out"
                )
    commit = git_revision()
    others = sorted({str(r.get("commit") or "unrecorded") for r in runs} - {str(commit)})
    if others:
        print(
            f"--resume: {path} holds runs of commit {', '.join(others)}; this sweep runs {commit} "
            "(each run's log keeps its commit)",
            file=sys.stderr,
        )
    sweeps.append(
        {
            "commit": commit,
            "host": platform.node(),
            "workers": args.workers,
            "ray": args.ray,
            "argv": sys.argv[1:],
        }
    )
    todo = [c for c in grid if _key(c) not in earlier]
    results = (_run_ray if args.ray else _run_local)(todo, args.workers)
    failed = []
    # SIGTERM (kill, timeout) ends the sweep as Ctrl-C does: the pool's running runs end with it
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        for r in tqdm(results, total=len(todo), desc="sweep"):
            c = r["config"]
            if "error" in r:
                failed.append(r)
                tqdm.write(f"{c['task']} {c['model']} seed {c['seed']}: FAILED {r['error']}")
                _write(args.out / "failed.json", failed)
                continue
            runs.append(r)
            _write(path, {"runs": runs, "sweeps": sweeps})
            s = r["summary"]
            end = s.get("loss_end", s.get("loss_executed"))
            start = s.get("loss_start", s.get("loss_zero_actions"))
            tqdm.write(
                f"{c['task']} {c['model']} seed {c['seed']}: loss {start:.6g} -> {end:.6g}, {s['wall_s']:.0f} s"
            )
    except KeyboardInterrupt:
        results.close()  # ends the pool's runs (a run in this process has ended already)
        _write(path, {"runs": runs, "sweeps": sweeps})
        print(f"interrupted: {len(runs)} runs in {path}; --resume runs the rest", file=sys.stderr)
        sys.exit(130)
    _write(path, {"runs": runs, "sweeps": sweeps})  # (also when every run failed: the file says so)
    if not failed:  # failed.json lists this sweep's failures only: none now
        (args.out / "failed.json").unlink(missing_ok=True)
    print(
        f"{len(runs)} runs in {path}"
        + (f"; {len(failed)} failed, in {args.out / 'failed.json'}" if failed else "")
    )
    if failed:  # (the exit status says it too, for scripts that chain sweeps)
        sys.exit(1)


if __name__ == "__main__":
    main()
