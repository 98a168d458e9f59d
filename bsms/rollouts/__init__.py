"""Rollouts and what they are measured by, shared by training's validation, the evaluation and
inference.

- :mod:`bsms.rollouts.rollout`: a learned simulator stepped autoregressively from frame 0, and
  the metrics of a rollout against the solver's;
- :mod:`bsms.rollouts.learned_rollouts`: learned rollouts of stored trajectories, timed and
  scored (what ``bsms.evaluate`` reports and ``train.validation: rollout`` validates on);
- :mod:`bsms.rollouts.solver_runs`: the MPM solver run again on a stored trajectory, at the data's
  own settings and cheaper ones;
- :mod:`bsms.rollouts.motion`: rigid and deformation parts of motion and error, the skill against
  predicting no motion;
- :mod:`bsms.rollouts.memory`: freed memory kept for reuse in long rollout loops;
- :mod:`bsms.rollouts.viz`: the pictures and files a person looks at (GIFs, curves, charts, XDMF).
"""
