"""The experiments' vocabulary: the contact models, the optimisers, the losses and every setting of a run with its
default (the tasks' names are the library's: ``cfd_torch.envs.TASKS``).

Without torch or the library, so that the scripts that only read settings (``plot_results.py``) start at once.
"""

from __future__ import annotations

TASK_KWARGS = {"Billiards": {"target_ball": 14, "pocket": 1}}
OPTIMISERS = ("ngd", "adam", "ngd-ls")
LOSSES = ("sum", "final", "closest")

MODELS = ("cfd", "ipc", "sdrs", "gb", "mujoco-fd")
FD_STEPS = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5)  # mujoco-fd: the step sizes its sweep tries

# every key run_experiment reads, with its default (the command line's defaults are these)
DEFAULTS = {
    "task": "Billiards", "model": "cfd", "seed": 0, "iters": 30, "horizon": 40, "mpc": False, "steps": 100,
    "knots": None, "dt": None, "eps": None, "lr": 0.1, "optimizer": "ngd", "gb_samples": 16, "gb_sigma": 0.1,
    "fd_step": None, "mj_substeps": 10, "threads": None, "loss": "sum", "lr_final": None,
    "smooth_samples": 0, "smooth_sigma": 0.1, "task_args": None, "theta_max": None,
    "out": None, "gif": True,
}  # fmt: skip

# the settings only one model reads (the others' runs are the same whatever they are): setting -> model
MODEL_ONLY = {"gb_samples": "gb", "gb_sigma": "gb", "fd_step": "mujoco-fd", "mj_substeps": "mujoco-fd"}


def unused_settings(cfg: dict, models, model_only: bool = True) -> tuple[str, str] | None:
    """The first setting of ``cfg`` given a value other than its default that no run of ``models`` would read, as
    (its option, why), or None: such a value was silently dropped (``--steps`` without ``--mpc``, ``--gb-samples``
    for a cfd run). ``model_only`` False skips the settings of :data:`MODEL_ONLY` (a resumed sweep's earlier runs
    may be of their model)."""

    def given(key: str) -> bool:
        return cfg.get(key, DEFAULTS[key]) != DEFAULTS[key]

    def opt(key: str) -> str:
        return "--" + key.replace("_", "-")

    if given("steps") and not cfg.get("mpc"):
        return opt("steps"), "the number of MPC control steps: it applies with --mpc"
    if given("smooth_sigma") and not cfg.get("smooth_samples"):
        return opt("smooth_sigma"), "it applies with --smooth-samples"
    for key, model in MODEL_ONLY.items() if model_only else ():
        if given(key) and model not in models:
            return opt(key), f"it applies to the model {model} only"
    if cfg.get("eps") is not None and not set(models) - {"ipc", "sdrs"}:
        return "--eps", "this library's blend width: the ipc and sdrs models do not read it"
    return None
