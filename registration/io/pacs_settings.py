"""Where a PACS is and how to sign in: :class:`PacsSettings` (URL, credentials, CA bundle) from the
environment or a config file that others cannot read, never from the command line; credentials
only over HTTPS or to this machine. Errors are :class:`PacsError` (a ``ValueError``).
"""

from __future__ import annotations

import ipaddress
import json
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

ENV_URL = "ROADMAP3D_PACS_URL"


ENV_USERNAME = "ROADMAP3D_PACS_USERNAME"


ENV_PASSWORD = "ROADMAP3D_PACS_PASSWORD"


ENV_CA_BUNDLE = "ROADMAP3D_PACS_CA_BUNDLE"


ENV_CONFIG = "ROADMAP3D_PACS_CONFIG"
#: Seconds to wait for the server (connect, read).
DEFAULT_TIMEOUT_S = (5.0, 120.0)


class PacsError(ValueError):
    """A PACS that cannot be reached, refuses a request or answers something unusable."""


def default_config_path() -> Path:
    """``ROADMAP3D_PACS_CONFIG``, else ``<user config dir>/roadmap3d/pacs.json``."""
    env = os.environ.get(ENV_CONFIG)
    if env:
        return Path(env).expanduser()
    from platformdirs import user_config_dir

    return Path(user_config_dir("roadmap3d")) / "pacs.json"


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class PacsSettings:
    """Where the DICOMweb service is and how to log in (the password never shows in ``repr``)."""

    url: str
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    ca_bundle: Path | None = None
    timeout_s: tuple[float, float] = DEFAULT_TIMEOUT_S
    #: Requests are tried this often (exponential back-off) when the server is busy or unreachable.
    attempts: int = 3

    def __post_init__(self) -> None:
        parts = urlsplit(self.url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise PacsError(f"PACS URL must be http(s)://host[:port]/path, got {self.display_url!r}")
        if parts.username is not None or parts.password is not None:
            raise PacsError(
                f"PACS URL {self.display_url}: credentials in the URL are refused; set "
                f"{ENV_USERNAME}/{ENV_PASSWORD} or the config file ({default_config_path()})"
            )
        if (self.username is None) != (self.password is None):
            raise PacsError(f"PACS {self.display_url}: a username needs a password and vice versa")
        if self.username is not None and parts.scheme != "https" and not _is_loopback(parts.hostname):
            raise PacsError(
                f"PACS {self.display_url}: refusing to send credentials over plain HTTP to another machine; use https://"
            )
        if self.ca_bundle is not None:
            if parts.scheme != "https":
                raise PacsError(f"PACS {self.display_url}: a CA bundle applies to https:// URLs only")
            if not Path(self.ca_bundle).is_file():
                raise PacsError(f"CA bundle {self.ca_bundle}: no such file")

    @property
    def display_url(self) -> str:
        """The URL without any user information (safe for messages and logs)."""
        parts = urlsplit(self.url)
        host = parts.hostname or ""
        netloc = host if parts.port is None else f"{host}:{parts.port}"
        return parts._replace(netloc=netloc).geturl()

    @classmethod
    def resolve(
        cls,
        url: str | None,
        *,
        ca_bundle: str | os.PathLike[str] | None = None,
        config: str | os.PathLike[str] | None = None,
        environ: dict[str, str] | None = None,
    ) -> PacsSettings:
        """Settings for ``url`` (or the environment's / config file's URL when None).

        Credentials: the environment first (``ROADMAP3D_PACS_USERNAME``/``_PASSWORD``), else the
        config file's entry. The config file is JSON, either one object
        ``{"url": ..., "username": ..., "password": ..., "ca_bundle": ...}`` or a list of them
        (the entry whose url matches is used); it must not be readable by others when it holds a
        password.
        """
        env = os.environ if environ is None else environ
        path = Path(config).expanduser() if config is not None else default_config_path()
        entries = _read_config(path) if (config is not None or path.is_file()) else []
        url = url or env.get(ENV_URL) or (entries[0].get("url") if len(entries) == 1 else None)
        if not url:
            raise PacsError(f"no PACS URL: give --pacs URL, set {ENV_URL} or write it into {path}")
        entry = next((e for e in entries if str(e.get("url", "")).rstrip("/") == url.rstrip("/")), {})
        username = env.get(ENV_USERNAME) or entry.get("username")
        password = env.get(ENV_PASSWORD) or entry.get("password")
        bundle = ca_bundle or env.get(ENV_CA_BUNDLE) or entry.get("ca_bundle")
        return cls(
            url=url,
            username=username,
            password=password,
            ca_bundle=Path(bundle).expanduser() if bundle else None,
        )


def _read_config(path: Path) -> list[dict[str, Any]]:
    try:
        info = path.stat()
        text = path.read_text()
    except OSError as exc:
        raise PacsError(f"PACS config {path}: cannot read it ({exc.strerror})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise PacsError(f"PACS config {path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    entries = data if isinstance(data, list) else [data]
    if not all(isinstance(e, dict) for e in entries):
        raise PacsError(f"PACS config {path}: expected an object or a list of objects")
    if any("password" in e for e in entries) and info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise PacsError(f"PACS config {path}: holds a password but others can read it; chmod 600 {path}")
    return entries
