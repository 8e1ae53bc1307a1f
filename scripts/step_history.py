"""What each optimisation bought: one ``bench_step.py`` case timed at a list of git revisions, in one run.

Every revision (and the working tree, last) runs the case in its own subprocess with ``bench_step.py``'s worker
(``--baseline`` machinery: a git worktree of the revision, PYTHONPATH at it, the working tree's scene definition), so
all of them step the same scene from the same start. Per revision: the median forward (the ``step()`` call), forward
+ backward, Newton iterations and contact evaluations per step. The revisions alternate over ``--runs`` rounds and
the table gives the median of their medians (the machine is shared and noisy).

Writes ``<out>/step_history.json``, ``<out>/step_history.md`` (printed too) and ``<out>/step_history.png``.

    python scripts/step_history.py --case billiards16 --revs 4b00007 4f21ded 6a773f0 --out results/step_history
    python scripts/step_history.py --case boxes4 --revs 4b00007 --bench-args="--quick --steps 5"
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from tqdm import tqdm  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_step  # noqa: E402
from _cli import positive_int  # noqa: E402


def _row(res: dict) -> dict:
    if "error" in res:
        return {"error": res["error"]}
    f = res["forward"]
    return {
        "forward_s": f.get("call_s", f["total_s"]),
        "forward_backward_s": res.get("forward_backward_s"),
        "newton_iters": f.get("newton_iters_median"),
        "contact_evals": f.get("contact_evals_median"),
        "newton_iters_all": f.get("newton_iters_all"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="billiards16", help="a bench_step.py case name")
    ap.add_argument("--revs", nargs="+", required=True, help="git revisions, oldest first")
    ap.add_argument(
        "--labels", nargs="+", default=None, help="one label per revision (default: the revision)"
    )
    ap.add_argument("--runs", type=positive_int, default=1, help="rounds over all revisions")
    ap.add_argument("--out", type=Path, default=Path("results/step_history"), help="output folder")
    ap.add_argument(
        "--bench-args", default="",
        help="extra bench_step.py arguments as one string: --bench-args='--billiards-steps 6 --quick' (the "
        "'=' form; the next word is taken as the value in any case, though it starts with '-')",
    )  # fmt: skip
    argv = sys.argv[1:]
    for i in range(len(argv) - 2, -1, -1):  # argparse would read a value starting with '-' as an option
        if argv[i] == "--bench-args":
            argv[i : i + 2] = [f"--bench-args={argv[i + 1]}"]
    args = ap.parse_args(argv)
    labels = args.labels or args.revs
    if len(labels) != len(args.revs):
        ap.error(f"argument --labels: needs one label per revision ({len(args.revs)}), got {len(labels)}")
    family = next((f for f in bench_step.CASES if args.case.startswith(f)), None)
    if family is None:
        ap.error(
            f"argument --case: {args.case!r} is not a case of bench_step.py's {', '.join(bench_step.CASES)}"
        )
    bargs = bench_step.parse_args(
        ["--cases", family, *args.bench_args.split()], prog=f"{ap.prog} --bench-args (bench_step.py)"
    )
    try:
        names = [c.name for c in bench_step.make_cases(bargs)]
    except bench_step.SettingsError as err:
        ap.error(f"argument --bench-args: {err}")
    if args.case not in names:
        ap.error(f"argument --case: no case {args.case!r} in bench_step.py (cases of {family!r}: {names})")
    args.out.mkdir(parents=True, exist_ok=True)
    revs = [bench_step.Baseline(r) for r in args.revs]
    runs: dict[str, list[dict]] = {lab: [] for lab in [*labels, "working tree"]}
    try:
        todo = [
            (k, lab, rev)
            for k in range(args.runs)
            for lab, rev in [*zip(labels, revs, strict=True), ("working tree", None)]
        ]
        for _, lab, rev in tqdm(todo, desc=args.case):
            if rev is None:
                cases = [c for c in bench_step.make_cases(bargs) if c.name == args.case]
                res = bench_step.run_case(cases[0], bargs)
            else:
                res = rev.run(args.case, bargs)
            runs[lab].append(_row(res))
    finally:
        for r in revs:
            r.close()
    commits = {lab: r.commit for lab, r in zip(labels, revs, strict=True)}
    table = {}
    for lab, rows in runs.items():
        good = [r for r in rows if "error" not in r]
        if not good:
            table[lab] = {"error": rows[0]["error"] if rows else "no run"}
            continue
        table[lab] = {
            k: statistics.median(r[k] for r in good)
            for k in ("forward_s", "forward_backward_s", "newton_iters", "contact_evals")
            if all(r.get(k) is not None for r in good)
        }
    first = table[labels[0]].get("forward_s")
    lines = [
        f"{args.case}: medians over the timed steps, median over {args.runs} round(s); speed-up = forward of "
        f"{labels[0]} / forward",
        "",
        "| revision | commit | forward ms | forward + backward ms | Newton it | evals | speed-up |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for lab, t in table.items():
        if "error" in t:
            lines.append(f"| {lab} | {commits.get(lab, '-')} | failed: {t['error'][-80:]} | | | | |")
            continue
        fb = t.get("forward_backward_s")
        lines.append(
            f"| {lab} | {commits.get(lab, '-')} | {1e3 * t['forward_s']:.0f} | "
            f"{'-' if fb is None else f'{1e3 * fb:.0f}'} | {t.get('newton_iters', '-')} | "
            f"{t.get('contact_evals', '-')} | {first / t['forward_s']:.1f}x |"
        )
    text = "\n".join(lines)
    print(text)
    (args.out / "step_history.md").write_text(text + "\n")
    (args.out / "step_history.json").write_text(
        json.dumps(
            {"case": args.case, "revs": args.revs, "commits": commits, "runs": runs, "table": table}, indent=1
        )
    )
    ok = [lab for lab in table if "error" not in table[lab]]
    fig, ax = plt.subplots(figsize=(1.2 * len(ok) + 2, 4))
    ax.bar(range(len(ok)), [1e3 * table[lab]["forward_s"] for lab in ok])
    ax.set_xticks(range(len(ok)), ok, rotation=30, ha="right")
    ax.set_ylabel("forward ms per step (median)")
    ax.set_title(args.case)
    fig.tight_layout()
    fig.savefig(args.out / "step_history.png", dpi=120)


if __name__ == "__main__":
    main()
