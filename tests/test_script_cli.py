"""The scripts' command lines: presets (``--quick``) fill only the options the command line does not give
(scripts/_cli.py), and bad values are refused with argparse's usage error naming the option."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest
import torch


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    p.add_argument("--quick", action="store_true")
    p.add_argument("--phases", type=int, default=16)
    p.add_argument("--schemes", nargs="+", default=["plain"])
    p.add_argument("--out", type=Path, default=Path("results/x"))
    return p


def test_a_preset_keeps_an_option_given_with_its_default_value(scripts_path):
    from _cli import apply_preset, given

    p = _parser()
    argv = ["--quick", "--phases", "16"]  # the default value, given explicitly
    assert given(p, argv) == {"quick", "phases"}
    args = p.parse_args(argv)
    apply_preset(p, args, {"phases": 8, "schemes": ["sub:4"]}, argv)
    assert args.phases == 16 and args.schemes == ["sub:4"] and args.out == Path("results/x")
    # the parser's defaults are restored after the probe
    assert p.parse_args([]).phases == 16 and p.get_default("schemes") == ["plain"]


def test_stacked_books_quick_keeps_an_explicit_board_count(scripts_path, monkeypatch):
    import stacked_books

    monkeypatch.setattr(sys, "argv", ["stacked_books.py", "--quick", "--boards", "20"])
    assert stacked_books.parse_args().boards == 20
    monkeypatch.setattr(sys, "argv", ["stacked_books.py", "--quick"])
    assert stacked_books.parse_args().boards == 5


def test_the_number_types_accept_their_range_only(scripts_path):
    from _cli import int_range, nonnegative_float, nonnegative_int, positive_float, positive_int

    assert positive_int("3") == 3 and nonnegative_int("0") == 0 and int_range(1, 5)("5") == 5
    assert positive_float("1e-8") == 1e-8 and nonnegative_float("0") == 0.0
    refused = [(positive_int, "0"), (positive_int, "1.5"), (nonnegative_int, "-1"), (int_range(1, 5), "6"),
               (positive_float, "0"), (positive_float, "nan"), (positive_float, "inf"), (nonnegative_float, "-1e-9"),
               (nonnegative_float, "x")]  # fmt: skip
    for parse, text in refused:
        with pytest.raises(argparse.ArgumentTypeError, match=f"got '{text}'"):
            parse(text)


def test_the_device_type_takes_a_usable_torch_device(scripts_path):
    import torch
    from _cli import torch_device

    assert torch_device("cpu") == torch.device("cpu")
    for text in ("foo", "meta", "cuda:x"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"must be cpu, cuda or cuda:N, got '{text}'"):
            torch_device(text)
    if not torch.cuda.is_available():
        with pytest.raises(argparse.ArgumentTypeError, match="'cuda:1' is not available here"):
            torch_device("cuda:1")


# (script, arguments, the option its error must name): each is refused while the command line is parsed, before the
# output folder is made or any work starts
REFUSED = [
    ("impact_phase", ["--quick", "--phases", "2", "--substeps", "0"], "--substeps"),
    ("impact_phase", ["--dts", "-0.01"], "--dts"),
    ("impact_phase", ["--phases", "0"], "--phases"),
    (
        "impact_phase",
        ["--quick", "--gap0", "0"],
        "--gap0",
    ),  # within the contact margin: a ValueError traceback
    ("impact_phase", ["--quick", "--gap0", "0.0005"], "--gap0"),
    ("impact_phase", ["--quick", "--gap0", "0.5"], "--duration"),  # no impact by 0.3 s: e = -1, bias 0
    ("impact_phase", ["--quick", "--speeds", "0.01"], "--duration"),  # a far-field bounce: e = 2
    ("bench_contact", ["--repeats", "-1"], "--repeats"),
    ("bench_contact", ["--repeats", "0"], "--repeats"),
    ("bench_contact", ["--brute-max-s", "0"], "--brute-max-s"),
    ("articulated_accuracy", ["--quick", "--duration", "0"], "--duration"),
    ("stacked_books", ["--threads", "0"], "--threads"),
    ("stacked_books", ["--boards", "-2"], "--boards"),
    ("stacked_books", ["--mu", "-1"], "--mu"),
    ("stacked_books", ["--dt", "0"], "--dt"),
    ("stacked_books", ["--t-min", "30"], "--t-min"),  # never at rest: every run 'unstable'
    ("stacked_books", ["--rest-time", "25"], "--rest-time"),
    ("step_history", ["--revs", "HEAD", "--runs", "0"], "--runs"),
    ("bench_step", ["--num-boxes", "0"], "--num-boxes"),
    ("bench_step", ["--num-cubes", "0"], "--num-cubes"),
    ("bench_step", ["--num-balls-rows", "7"], "--num-balls-rows"),
    ("bench_step", ["--cube-size", "-0.05"], "--cube-size"),
    ("bench_step", ["--friction", "-0.5"], "--friction"),
    ("bench_step", ["--profile", "--profile-steps", "0"], "--profile-steps"),
    ("bench_step", ["--friction-eps-v", "0"], "--friction-eps-v"),
    ("bench_step", ["--friction-eps-v", "1e-40"], "--friction-eps-v"),  # below FrictionConfig's 1e-30
    ("bench_step", ["--numba-threads", "100000"], "--numba-threads"),  # numba's own ValueError, a traceback
    ("far_field_directions", ["--angles", "0"], "--angles"),
    ("far_field_directions", ["--horizon", "0"], "--horizon"),
    ("far_field_directions", ["--radii", "-1"], "--radii"),
    ("far_field_staircase", ["--points", "0"], "--points"),
    ("far_field_staircase", ["--eps", "-1"], "--eps"),
    ("impact_model_1d", ["--phases", "0"], "--phases"),
    ("impact_model_1d", ["--schemes", "sub:0"], "--schemes"),
    ("impact_model_1d", ["--schemes", "foo"], "--schemes"),
    ("impact_model_1d", ["--dt", "-0.01"], "--dt"),
    ("impact_model_1d", ["--quick", "--gap0", "0.0005"], "--gap0"),  # e = 0.0000 at phase 0, bias 3.5
    ("impact_model_1d", ["--quick", "--gap0", "0.5"], "--duration"),  # e = -1, bias -0.000
    ("impact_model_1d", ["--quick", "--speed", "0.01"], "--duration"),  # e = 2, negative predicted bias
    ("impact_model_1d", ["--schemes", "aligned:0.05:1"], "--schemes"),  # G above gap0: silently plain
    ("stress", ["--seed", "-1"], "--seed"),
    ("bench_pair", ["--device", "foo"], "--device"),
    ("bench_device", ["--device", "cpu"], "--device"),  # the CPU is the other side of the comparison
    ("bench_device", ["--batches", "0"], "--batches"),
    ("bench_device", ["--budget-s", "0"], "--budget-s"),
    ("profile_task_step", ["--cases", "Pool:1"], "--cases"),
    ("profile_task_step", ["--cases", "Push:0"], "--cases"),
    ("profile_task_step", ["--device", "foo"], "--device"),
    ("demo_pair", ["--margin", "-1"], "--margin"),
    ("demo_billiards", ["--dt", "-1"], "--dt"),
    ("push_reach", ["--dt", "-0.01"], "--dt"),
    ("push_reach", ["--box-density", "-5"], "--box-density"),
    ("push_reach", ["--distance", "-1"], "--distance"),
    ("render_envs", ["--size", "0"], "--size"),
    ("render_envs", ["--steps", "-1"], "--steps"),
    ("billiards_landscape", ["--shot-steps", "0"], "--shot-steps"),
    ("bench_envs", ["--num-envs", "0"], "--num-envs"),
    ("bench_rollout", ["--horizons", "50", "0"], "--horizons"),
    ("bench_rollout", ["--runs", "0"], "--runs"),
    ("bench_rollout", ["--action-scale", "-0.5"], "--action-scale"),
    ("bench_rollout", ["--tasks", "Pool"], "--tasks"),
    ("sweep", ["--seeds", "0", str(2**64)], "--seeds"),  # the second seed: only the first was checked
    # settings the run (or every run of the sweep) does not read: each was silently dropped
    ("optimize", ["--steps", "5"], "--steps"),  # without --mpc
    ("optimize", ["--gb-samples", "-3"], "--gb-samples"),  # a cfd run
    ("optimize", ["--smooth-sigma", "0.5"], "--smooth-sigma"),  # without --smooth-samples
    ("optimize", ["--model", "ipc", "--eps", "0.5"], "--eps"),
    ("sweep", ["--models", "cfd", "gb", "--mj-substeps", "3"], "--mj-substeps"),
    # each of these raised a traceback after measuring (the first) or building the output folder (the others)
    ("bench_step", ["--quick", "--cases", "boxes", "--baseline", "no-such-rev"], "--baseline"),
    ("bench_step", ["--quick", "--cases", "push", "--push-speed", "0"], "--push-speed"),  # ZeroDivisionError
    ("bench_step", ["--quick", "--cases", "push", "--push-gap", "0.0005"], "--push-gap"),  # within the margin
    ("bench_step", ["--quick", "--cases", "cubes", "--cube-drop", "0.0002", "0.0005"], "--cube-drop"),
    ("articulated_accuracy", ["--quick", "--cases", "bar", "--baseline", "no-such-rev"], "--baseline"),
    ("demo_pair", ["--dhat", "0.001"], "--dhat"),  # no local-barrier force at the smallest gap to scale by
    ("far_field_directions", ["--radii", "0.1", "--angles", "2", "--horizon", "1"], "--radii"),  # in the box
    ("billiards_landscape", ["--angles", "-15", "20", "1"], "--angles"),  # a blank heat map
    ("stress_step", ["--duration", "inf"], "--duration"),
    ("step_accuracy", ["--replot"], "--replot"),  # no JSON in --out
    ("trivial_start_runs", ["--tasks", "Push", "Push"], "--tasks"),  # ran and tabulated twice
    ("rolling_ball", ["--dt", "0.01", "0"], "--dt"),
    ("rolling_ball", ["--subdivisions", "7"], "--subdivisions"),
    ("bench_bodies", ["--layout", "pile", "--steps", "3"], "--steps"),  # the landing steps are 4 and later
    ("bench_bodies", ["--sizes", "0"], "--sizes"),
    ("rest_gaps", ["--steps", "10"], "--steps"),  # the rest test looks at the last 20
    ("rest_gaps", ["--sizes", "0.5", "--floor", "1"], "--floor"),  # the floor must reach past the bodies
    ("rest_gaps", ["--mu", "0"], "--mu"),
]


@pytest.mark.parametrize(
    ("script", "argv", "option"), REFUSED, ids=[f"{s} {' '.join(a)}" for s, a, _ in REFUSED]
)
def test_a_script_refuses_a_bad_option_while_parsing(
    scripts_path, monkeypatch, capsys, tmp_path, script, argv, option
):
    import importlib

    module = importlib.import_module(script)
    out = tmp_path / "out"

    def no_mkdir(self, *args, **kwargs):
        raise AssertionError(f"{script} went on to make {self} with {argv}")

    monkeypatch.setattr(Path, "mkdir", no_mkdir)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv, "--out", str(out)])
    with pytest.raises(SystemExit) as exit_:
        module.main()
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"error: argument {option}:" in err, err
    assert not out.exists()


def test_plot_results_refuses_an_out_that_is_a_file(scripts_path, monkeypatch, capsys, tmp_path):
    """As optimize.py and sweep.py do (it raised FileExistsError from mkdir)."""
    import plot_results

    afile = tmp_path / "afile"
    afile.write_text("")
    monkeypatch.setattr(sys, "argv", ["plot_results.py", str(tmp_path), "--out", str(afile / "sub")])
    with pytest.raises(SystemExit) as exit_:
        plot_results.main()
    assert exit_.value.code == 2
    assert f"error: --out {afile / 'sub'}: {afile} is a file; give a folder" in capsys.readouterr().err


def test_an_out_folder_that_cannot_be_written_is_refused(scripts_path, tmp_path):
    """Beside a file in the way: a folder the process cannot make, and a link to nothing (they raised from mkdir
    or from the first file written, after the first rollout)."""
    from _cli import folder_problem

    assert folder_problem(tmp_path / "new" / "sub") is None
    assert list(tmp_path.iterdir()) == []  # the check leaves nothing behind
    if Path("/proc/self").is_dir():  # Linux: no folder can be made in /proc, not even by root
        assert folder_problem(Path("/proc/cfd-out")).startswith("/proc/cfd-out: cannot write in /proc (")
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "gone")
    assert folder_problem(link) == f"{link}: a link to {tmp_path / 'gone'}, which does not exist"


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "not a readable JSON file"),
        ("[1, 2]", "not a sweep.json"),
        ('{"runs": null}', "not a sweep.json"),
        ('{"runs": [1]}', "run 0 has no config naming its task, model and seed"),
        ('{"runs": [{"config": {"task": "Push"}}]}', "run 0 has no config naming its task, model and seed"),
        # a run without its log or summary: a bare KeyError or IndexError while plotting
        (
            '{"runs": [{"config": {"task": "Push", "model": "cfd", "seed": 0}, "summary": {}}]}',
            "run 0 has no log (a non-empty list of its iterations)",
        ),
        (
            '{"runs": [{"config": {"task": "Push", "model": "cfd", "seed": 0}, "log": [], "summary": {}}]}',
            "run 0 has no log",
        ),
        (
            '{"runs": [{"config": {"task": "Push", "model": "cfd", "seed": 0}, "log": [{"loss": 1.0}]}]}',
            "run 0 has no summary",
        ),
    ],
)
def test_plot_results_refuses_a_malformed_sweep_json(
    scripts_path, monkeypatch, capsys, tmp_path, text, message
):
    """A usage error saying what is wrong (a traceback from inside the loop before)."""
    import plot_results

    (tmp_path / "sweep.json").write_text(text)
    monkeypatch.setattr(sys, "argv", ["plot_results.py", str(tmp_path), "--out", str(tmp_path / "plots")])
    with pytest.raises(SystemExit) as exit_:
        plot_results.main()
    assert exit_.value.code == 2
    assert f"{tmp_path / 'sweep.json'}: {message}" in capsys.readouterr().err


@pytest.mark.parametrize("script", ["stacked_books", "impact_phase", "impact_model_1d", "rolling_ball"])
def test_an_experiment_script_refuses_an_out_that_is_a_file(
    scripts_path, monkeypatch, capsys, tmp_path, script
):
    """As plot_results.py does (they raised NotADirectoryError from mkdir after parsing)."""
    import importlib

    module = importlib.import_module(script)
    afile = tmp_path / "afile"
    afile.write_text("")
    monkeypatch.setattr(sys, "argv", [f"{script}.py", "--quick", "--out", str(afile / "sub")])
    with pytest.raises(SystemExit) as exit_:
        module.main()
    assert exit_.value.code == 2
    assert (
        f"error: argument --out: {afile / 'sub'}: {afile} is a file; give a folder" in capsys.readouterr().err
    )


def _strict_json(path: Path) -> dict:
    """The JSON file at ``path``, refusing NaN and +-Infinity (not JSON: most parsers other than Python's fail)."""
    import json

    def refuse(token: str):
        raise AssertionError(f"{path}: {token} is not JSON")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_stacked_books_records_its_checkout_and_writes_strict_json(scripts_path, monkeypatch, tmp_path):
    """Run from another folder with its first step failing: the JSON names the scripts' checkout's commit (it ran
    git in the working directory: another repository's commit, or none) and writes null, not Infinity, for the
    measures no step gave."""
    import stacked_books
    from _provenance import git_revision

    monkeypatch.chdir(tmp_path)
    argv = ["--quick", "--mu", "1e-8", "--max-newton-iter", "1", "--substeps", "0", "--t-max", "0.5", "--t-min",
            "0", "--rest-time", "0.2", "--out", str(tmp_path / "out")]  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["stacked_books.py", *argv])
    stacked_books.main()
    out = _strict_json(tmp_path / "out" / "stacked_books.json")
    assert out["cfd_torch_commit"] == git_revision() is not None
    (row,) = out["results"]
    assert not row["stable"] and row["smallest_support_margin_m"] is None


def _gif_frames(path: Path) -> tuple[int, tuple[int, int]]:
    from PIL import Image

    with Image.open(path) as gif:
        return gif.n_frames, gif.size


def test_stacked_books_writes_a_gif_of_each_run_unless_told_not_to(scripts_path, monkeypatch, tmp_path):
    """Motion is shown, not only tabled: one GIF per mu, one frame per step from the start (``run`` returns the
    poses of every step), and ``--no-gif`` writes none."""
    import argparse

    import stacked_books

    argv = [
        "--quick",
        "--boards",
        "2",
        "--mu",
        "1e-8",
        "--t-max",
        "0.3",
        "--t-min",
        "0.3",
        "--rest-time",
        "0.1",
    ]
    monkeypatch.setattr(sys, "argv", ["stacked_books.py", *argv, "--out", str(tmp_path / "a")])
    args = stacked_books.parse_args()
    record, poses = stacked_books.run(argparse.Namespace(**vars(args)), 1e-8)
    assert record["steps"] == 3 and poses.shape == (4, 3, 6)
    _, poses0, _, _ = stacked_books.build(args, 1e-8)
    assert torch.equal(poses[0], poses0) and not torch.equal(poses[-1], poses0)  # the boards moved
    stacked_books.main()
    frames, size = _gif_frames(tmp_path / "a" / "stacked_books_mu1e-08.gif")
    assert 2 <= frames <= 4 and size == (640, 320)  # identical consecutive frames merge
    monkeypatch.setattr(sys, "argv", ["stacked_books.py", *argv, "--out", str(tmp_path / "b"), "--no-gif"])
    stacked_books.main()
    assert (tmp_path / "b" / "stacked_books.json").exists() and not list((tmp_path / "b").glob("*.gif"))


def test_demo_billiards_shows_its_best_shot(scripts_path, monkeypatch, tmp_path, capsys):
    """The JSON names the best iterate beside the last, and the GIF shows the best one (one frame per step)."""
    import json

    import demo_billiards

    argv = ["--iters", "3", "--steps", "4", "--lr", "2.0", "--out", str(tmp_path)]
    monkeypatch.setattr(sys, "argv", ["demo_billiards.py", *argv])
    demo_billiards.main()
    out = json.loads((tmp_path / "billiards_demo.json").read_text())
    losses = [h["loss"] for h in out["history"]]
    assert out["best_loss"] == min(losses) and out["best_v"] == out["history"][out["best_iter"]]["v"]
    assert out["best_iter"] > 0 and out["best_v"] != [0.0, 0.0]  # the cue ball moved toward the pocket
    frames, size = _gif_frames(tmp_path / "billiards_demo.gif")
    assert 2 <= frames <= 5 and size == (400, 400)
    assert f"loss {out['best_loss']:.2e} (iteration {out['best_iter']})" in capsys.readouterr().out


def test_rolling_ball_starts_rolling_without_slipping_and_keeps_its_books(scripts_path):
    """The run's first record is the roll it set: speed v0 along x, spin v0 / (the centre's height) about y, and
    the energy is the sum of its parts."""
    import rolling_ball

    args = rolling_ball.parse_args(["--quick", "--duration", "0.05"])
    run = rolling_ball.roll(2, 0.01, args)
    h = run["history_t_energy_trans_rot_vx_spinr"]
    assert len(h) == 6 and run["faces"] == 320
    t, energy, trans, rot, vx, spin_r = h[0]
    assert (
        abs(vx - 2.0) < 1e-9 and abs(spin_r - 2.0) < 1e-5
    )  # (the settled rotation vector is not quite zero)
    import trimesh

    mass = 1000.0 * trimesh.creation.icosphere(subdivisions=2, radius=0.1).volume
    assert abs(trans - 0.5 * mass * 4.0) < 1e-8 * trans
    assert 0.3 < rot / trans < 0.45  # 2/5 (r / h)^2 for a solid ball: its spin set from the rolling radius
    potential = mass * rolling_ball.GRAVITY * run["rolling_radius_m"]  # (the settled centre's height)
    assert abs(energy - (trans + rot + potential)) < 1e-12 * energy and run["newton_iters"] > 0


def test_bench_bodies_times_each_size_and_names_the_library_it_timed(scripts_path, monkeypatch, tmp_path):
    import bench_bodies

    monkeypatch.setattr(
        sys, "argv", ["bench_bodies.py", "--sizes", "2", "3", "--steps", "2", "--out", str(tmp_path)]
    )
    bench_bodies.main()
    out = _strict_json(tmp_path / "bench_bodies.json")
    assert [r["n"] for r in out["rows"]] == [2, 3] and out["commit"] != "unknown"
    for r in out["rows"]:
        assert r["step_s"] > 0 and len(r["newton_iters"]) == 2 and min(r["contact_evals"]) >= 1
    assert (tmp_path / "bench_bodies.md").read_text().count("\n| ") == 3 and (
        tmp_path / "bench_bodies.png"
    ).exists()


def test_rest_gaps_compares_a_settled_rollout_with_the_prediction(scripts_path, tmp_path):
    """A 10 cm, 1 kg cube settles where rest_gap says (to 1 %), and the Scene did not warn of it; the tables and the
    plot are written."""
    import rest_gaps

    argv = [
        "--shapes",
        "cube",
        "--sizes",
        "0.1",
        "--densities",
        "1000",
        "--steps",
        "60",
        "--out",
        str(tmp_path),
    ]
    rest_gaps.main(argv)
    (row,) = _strict_json(tmp_path / "rest_gaps.json")["rows"]
    assert row["spread_last_20"] < 1e-7 and not row["warned"]
    assert abs(row["settled"] - row["predicted"]) < 0.01 * row["predicted"]  # observed 1.576 mm both
    assert (tmp_path / "rest_gaps.md").read_text().count("\n| cube 10 cm") == 1 and (
        tmp_path / "rest_gaps.png"
    ).exists()


def test_the_obstacle_ball_rests_on_a_ring_and_a_mesh_with_nothing_to_rest_on_is_refused(
    scripts_path, monkeypatch, capsys, tmp_path
):
    import bench_step
    import numpy as np
    import trimesh
    from _placement import ball_over, surface_heights

    # a ring centred on the origin: the default point, just off its centre, lies over the hole
    ring = trimesh.creation.annulus(r_min=0.3, r_max=1.0, height=0.2)
    x, y, z = ball_over(ring, 0.5, 2e-3)
    assert 0.3 < np.hypot(x, y) < 1.0  # over the ring itself
    assert np.isfinite(surface_heights(ring, np.array([[x, y]]))[0])
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    low = (ball.vertices + [x, y, z])[:, 2].min()
    assert 2e-3 - 1e-12 <= low - 0.1 < 2e-3 + 0.05  # above the ring's top face (z = 0.1) by the gap at least

    wall = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], [[0, 1, 2], [0, 2, 3]])
    path = tmp_path / "wall.stl"
    wall.export(path)
    out = tmp_path / "out"
    monkeypatch.setattr(
        sys,
        "argv",
        ["bench_step.py", "--quick", "--cases", "ball", "--obstacle", str(path), "--out", str(out)],
    )
    with pytest.raises(SystemExit) as exit_:
        bench_step.main()
    assert exit_.value.code == 2
    assert "error: argument --obstacle: every triangle of the obstacle is vertical" in capsys.readouterr().err
    assert not out.exists()


def test_bench_step_reports_a_failed_case_and_exits_with_status_1(scripts_path, monkeypatch, tmp_path):
    """Seven balls of 5 mm at the default stiffness (warned: they would rest 10.8 mm up) fail to step (the Newton
    cap, or a solution through another ball: which one follows the solver's rounding): the table and the JSON name
    the failure, and the script's status says so."""
    import bench_step

    monkeypatch.setattr(
        sys,
        "argv",
        [
            "bench_step.py",
            "--quick",
            "--cases",
            "billiards",
            "--num-balls-rows",
            "3",
            "--ball-radius",
            "0.005",
            "--out",
            str(tmp_path),
        ],  # fmt: skip
    )
    with (
        pytest.warns(UserWarning),
        pytest.raises(SystemExit, match="1 case\\(s\\) failed in this checkout: billiards7"),
    ):
        bench_step.main()
    out = _strict_json(tmp_path / "bench_step.json")
    err = out["cases"]["billiards7"]["error"]
    assert err.startswith(
        ("StepError: the step did not converge", "StepError: the step's solution is not reachable")
    )
    assert "| billiards7 | 7 x 320 + 19200 | failed: StepError" in (tmp_path / "table.md").read_text()
