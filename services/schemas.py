"""Schema types both services' requests and answers use, and `GET /config`'s answer: the
settings in force, never a secret."""

from __future__ import annotations

import typing
from typing import Annotated
from urllib.parse import parse_qsl, urlencode, urlsplit

from pydantic import (
    AfterValidator,
    BaseModel,
    Field,
    SecretBytes,
    SecretStr,
    Strict,
    create_model,
)


def _four_by_four(v: list[list[float]]) -> list[list[float]]:
    if len(v) != 4 or any(len(r) != 4 for r in v):
        raise ValueError("must be 4x4")
    return v


Matrix4 = Annotated[list[list[Annotated[float, Strict()]]], AfterValidator(_four_by_four)]
"""A 4x4 matrix in a JSON body, rows of numbers (pose or rigid transform): numbers only
(`true` and "1" were taken for 1.0: an outside tester's review)."""


def _not_empty(v: SecretStr) -> SecretStr:
    """An empty token turned access control on with a token no caller can send: every
    operator route answered 401 (an outside tester's review, session 51)."""
    if not v.get_secret_value():
        raise ValueError("is empty: set a token, or unset the variable for open access")
    return v


#: A token setting: a secret, never empty.
Token = Annotated[SecretStr, AfterValidator(_not_empty)]

#: A setting whose name holds one of these is never shown, whatever its type.
SECRET_WORDS = ("token", "password", "secret", "api_key", "credential")
REDACTED = "***"


def _holds_secret(tp) -> bool:
    """Whether a type is, or contains (`dict[str, SecretStr]`, `SecretStr | None`), a secret."""
    if tp in (SecretStr, SecretBytes):
        return True
    return any(_holds_secret(a) for a in typing.get_args(tp))


def _secret_name(name: str) -> bool:
    return any(w in name.lower() for w in SECRET_WORDS)


def redact_url(url: str) -> str:
    """A URL (or comma-separated replica URLs) without its password: `user:***@host`, and
    any query value whose name looks secret (`?password=`) as `***`; no fragment."""
    parts = []
    for one in url.split(","):
        u = urlsplit(one.strip())
        netloc = u.netloc
        if "@" in netloc:
            userinfo, _, host = netloc.rpartition("@")
            user, colon, _ = userinfo.partition(":")
            netloc = f"{user}:{REDACTED}@{host}" if colon else f"{userinfo}@{host}"
        query = [
            (k, REDACTED if _secret_name(k) else v)
            for k, v in parse_qsl(u.query, keep_blank_values=True)
        ]
        parts.append(
            u._replace(netloc=netloc, query=urlencode(query, safe="*"), fragment="").geturl()
        )
    return ",".join(parts)


class ConfigView:
    """`GET /config` of a service: its settings class's fields as resolved (defaults, then
    `FLEETMAP_...` variables, `.env`, secret files), minus every secret. A field holding a
    `SecretStr` or named like a secret (tokens) is left out; the fields in `urls` are shown
    with their password redacted (`redact_url`). `model`: the answer's pydantic model, for
    OpenAPI, built from the settings class so that a new setting shows up by itself."""

    def __init__(self, settings_cls, title: str, urls: tuple[str, ...] = ()):
        self.urls = urls
        fields: dict = {}
        for name, f in settings_cls.model_fields.items():
            if name in urls:
                fields[name] = (str | None, Field(description="a URL, its password redacted"))
            elif not (_holds_secret(f.annotation) or _secret_name(name)):
                fields[name] = (f.annotation, ...)
        self.model: type[BaseModel] = create_model(title, **fields)
        self.model.__doc__ = (
            "The settings in force (defaults and FLEETMAP_... variables), nested as the "
            "settings are; tokens left out, passwords in URLs redacted."
        )

    def answer(self, settings) -> BaseModel:
        values = {}
        for name in self.model.model_fields:
            v = getattr(settings, name)
            if name in self.urls and v is not None:
                plain = v.get_secret_value() if isinstance(v, SecretStr) else str(v)
                v = redact_url(plain)
            values[name] = v
        return self.model(**values)
