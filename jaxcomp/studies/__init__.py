"""The Monte-Carlo studies: thousands of simulated true robots on MJX, each with its own hidden
truth, run through calibration or the impedance controller and compared with that truth.

The library behind ``jaxcomp study``; it wires hardware (MJX), identify and control together, as
the command line does, and imports no click. Modules, one concept each:

- ``setup``: the studied robot and its shared MJX simulator;
- ``study_chunks``: a study's worlds in chunks, each finished chunk on disk, and the study run
  into its report folder (``into_folder``);
- ``processes``: a study over several processes (``jax.distributed``);
- ``calibration_settings``: what a calibration study runs (``CalibrationSettings``) and how its
  worlds are cut over the plans and the scipy sample;
- ``truth_draw``: the true robots of the calibration study (``TruthSpread``, ``draw_truth``);
- ``plan_signal``: a calibration plan as the 1 kHz signals the worlds follow, whole or cut
  into sweeps simulated side by side;
- ``plan_recording``: the plan recorded in every world, each sweep reduced to its moments as
  it streams in;
- ``calibration_estimates``: both fits' estimates against the truth;
- ``calibration_statistics``: their statistics over the worlds;
- ``calibration_report``: the report from the joined per-world arrays;
- ``calibration_figures``: the calibration study's figures;
- ``calibration``: the calibration study composed (simulate -> reduce -> fit -> report);
- ``calibration_outputs``: its files, its one call (``study_into``) and its summary;
- ``control_policy``: the impedance controller as a per-world closed-loop policy;
- ``control_worlds``: the control study's timeline, pushes, references, drawn worlds and
  model errors;
- ``control``: the control study (settings, the run, the report, its one call);
- ``control_figures``: the control study's figures.
"""
