"""The differentiable simulator: bodies, kinematics, the incremental potential, Newton, feasibility, the step."""
