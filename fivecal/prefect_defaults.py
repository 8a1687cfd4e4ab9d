"""Prefect settings fivecal's commands need, set before Prefect is first imported.

Prefect reads its settings from the environment once, when it is imported; a default set after
that import is ignored. ``fivecal/__init__.py`` imports this module first, so every ``fivecal``
command (and anything importing the ``fivecal`` package) gets these defaults unless the user has
set the variable.
"""

from __future__ import annotations

import os

# Prefect's temporary server starts in 10-20 s on 2 cores, later on a busy machine or with a new
# database, and by default Prefect gives up after 20 s ("Timed out while attempting to connect to
# ephemeral Prefect API server").
SERVER_STARTUP_TIMEOUT_S = 120

DEFAULTS = {
    # The temporary server would try to send telemetry; these machines have no network for it.
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": str(SERVER_STARTUP_TIMEOUT_S),
}

for _name, _value in DEFAULTS.items():
    os.environ.setdefault(_name, _value)
