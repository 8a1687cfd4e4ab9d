"""fivecal's Prefect defaults reach Prefect: they are set before Prefect reads its settings."""

import os
import subprocess
import sys

from fivecal.prefect_defaults import DEFAULTS, SERVER_STARTUP_TIMEOUT_S

PROBE = """
import fivecal.cli
from prefect.settings import (PREFECT_SERVER_ANALYTICS_ENABLED,
                              PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS)
print(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS.value(), PREFECT_SERVER_ANALYTICS_ENABLED.value())
"""


def _probe(**extra: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in DEFAULTS}
    env.update(extra)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_the_commands_server_timeout_and_telemetry_defaults_are_what_prefect_uses():
    assert _probe() == [str(SERVER_STARTUP_TIMEOUT_S), "False"]


def test_a_users_own_setting_wins():
    assert _probe(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS="45")[0] == "45"
