"""Where the runs of a suite execute: ``--backend local`` (processes here) or ``--backend ray``.

:mod:`~der_ros.experiments.backends.dispatch` holds :func:`run_specs` and the command-line glue;
``local``, ``ray_cluster``, ``artifacts`` and ``suite_progress`` the parts. Import the module you need.
"""
