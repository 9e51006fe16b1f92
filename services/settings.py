"""What both services' settings share: where secrets may come from, the refusal of
parameter names from before the settings were nested, and one line for a setting that
cannot be read."""

from __future__ import annotations

import dataclasses
import os

from fleetmap.errors import BadInput


def refuse_flat_names(prefix: str, params_class, nested: str, renamed=()) -> None:
    """Parameters are nested settings now (PREFIX_ALIGN__MIN_INLIERS); a variable of the
    old flat form (PREFIX_MIN_INLIERS) is refused with its new name, never ignored."""
    names = [(f.name, f.name) for f in dataclasses.fields(params_class)] + list(renamed)
    for was, now in names:
        old = f"{prefix}{was.upper()}"
        if old in os.environ:
            raise BadInput(f"{old} is no longer read: set {prefix}{nested}__{now.upper()} instead")


def secrets_dir() -> str | None:
    """Where settings may also come from files, one per variable named like it in lower case
    (`fleetmap_place_db_operator_token`): FLEETMAP_SECRETS_DIR, else Docker's /run/secrets
    where it exists. Tokens need not sit in the environment or in a compose file."""
    path = os.environ.get("FLEETMAP_SECRETS_DIR") or "/run/secrets"
    return path if os.path.isdir(path) else None


def unreadable(exc: Exception) -> BadInput | None:
    """One line naming the setting a pydantic ValidationError could not read (its variable's
    path after the prefix, what is wrong, what was given), or None for another error."""
    from pydantic import ValidationError
    from pydantic_settings import SettingsError

    if isinstance(exc, SettingsError):  # a variable pydantic-settings cannot parse (JSON)
        cause = f": {exc.__cause__}" if exc.__cause__ else ""
        return BadInput(f"setting: {exc}{cause}")
    if not isinstance(exc, ValidationError):
        return None
    err = exc.errors()[0]
    where = "__".join(str(p) for p in err["loc"]).upper()
    secret = any(w in where for w in ("TOKEN", "DATABASE"))  # a password never in a log
    given = "" if secret else f" (got {err.get('input')!r})"
    return BadInput(f"setting {where}: {err['msg']}{given}")
