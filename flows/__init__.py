"""Prefect flows: the jobs a user runs. Each wires tasks and does no maths itself.

Importing this package makes Prefect's temporary API server (started when no PREFECT_API_URL is
set) end with the process that started it, even a killed one (flows/server_guard.py).
"""

from flows import server_guard

server_guard.install()
