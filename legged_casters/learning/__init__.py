"""The learning extensions around rsl_rl, one idea per module: the actor with its prior and
estimator (models), the concurrent velocity estimator and its PPO (estimator), the runner
with safe checkpoints and the distributed override (runner), and the hooks train.py puts
around it: progress line, periodic evaluation, model_best.pt, wall-time budget (progress)."""
