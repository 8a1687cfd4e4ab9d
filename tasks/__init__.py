"""The work of fivecal, one sub-package per topic (docs/architecture.md gives the floors and the rules).

Science modules import no Prefect: a notebook can import them and nothing starts. The Prefect
``@task`` wrappers live in ``tasks.steps`` only.
"""
