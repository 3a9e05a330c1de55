"""Running a study: the launch, its Ray workers, the driver that records each trial.

Private modules: ``_launch`` (the launch sequence: checks, Ray, the claim, the sync,
exit codes), ``_signals`` (Ctrl-C and SIGTERM), ``_driver`` (the loop of a claimed
study), ``_execution`` (Ray worker actors and their typed events), ``_resources``
(whether the trials fit the cluster), ``_reaper`` (ends what is left of a local Ray
once its driver is gone), ``_progress``, ``_random_agent`` (the random baseline
measured once per study) and ``_confirm`` (the confirmation stage's plan against the
search's results). Commands: ``cli_launch``, ``cli_confirm``, ``cli_rerun``. Nothing
outside this package but ``sweeper.cli`` imports it, and this file imports nothing: a
Ray worker that loads ``_execution`` loads no more than it needs.
"""
