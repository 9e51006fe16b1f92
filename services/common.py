"""Names the CLI's `serve` and logging set-up import from here; what both services share now
lives by concern: `auth`, `body`, `http_errors`, `middleware`, `docs`, `serving`,
`settings`, `schemas` (and the aligner's pixel budget in `aligner.budget`)."""

from fleetmap.services.auth import auth_summary
from fleetmap.services.serving import JsonFormatter, check_port, header_timeout_protocol

__all__ = ["JsonFormatter", "auth_summary", "check_port", "header_timeout_protocol"]
