"""Identification of current/torque ratios, friction losses and centre-of-mass errors.

- ``plan``: calibration plans (sweeps, holds, speeds) and their JSON file;
- ``plan_checks``: what the robot's model finds wrong with a plan (load, floor, self-contact);
  ``plan_design``: the paper's plan, its held poses chosen on the robot's model;
- ``random_plans``: seeded random plans, to validate the fit on plans it was not tuned on;
  ``named_plans``: plans by name (default, short, random, random:K, a JSON file);
- ``recorder``: recording a plan on an ``Arm`` into a recording (``jaxcomp.recording``);
- ``steady``: the steady-sample rule (which samples of a sweep pass enter the fit);
- ``bins``: a recording's steady samples and their angle-bin means;
- ``moments``: sweep moments, a recording reduced exactly for the joint fit; ``packing``: the
  sweep samples laid out for the reduction; ``sweep_reduction``: the JAX reduction of packed
  samples to moments; ``streaming``: moments summed sample by sample during a simulation;
- ``fitting``: the entry point, ``fit`` and ``fit_each`` (re-exported here): recordings
  fitted by either method, the params checked;
- the joint JAX fit: ``fit_model`` (what it needs of the robot), ``fit_stats`` (the features of
  sweeps and transfers, reduced to sufficient statistics), ``fit_solver`` (priors and the
  solve), ``joint_fit`` (recordings fitted jointly into params), ``batched_fit`` (many
  recordings, each on its own, in vmapped batches);
- ``baseline``: the paper's fit (scipy, pinocchio);
- ``traced``: traced programs kept on disk between processes (``jax.export``);
- ``evaluate``: errors of fitted params against a known truth; ``plots``: calibration plots.

Identification reads recordings and writes a params file (``jaxcomp.robot_params``), the only
thing the controller takes from it.
"""

from jaxcomp.identify.fitting import fit, fit_each

__all__ = ["fit", "fit_each"]
