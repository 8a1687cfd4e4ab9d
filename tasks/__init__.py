"""The work of fivecal.

Science modules here import no Prefect: a notebook can import them and nothing starts.
Thin Prefect ``@task`` wrappers live in the ``*_steps`` modules only (``tasks.steps.calibration``,
``tasks.steps.dispensing``, ...).
"""
