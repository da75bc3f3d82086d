"""The web app's password file: a salted scrypt hash of the password, never the password.

Made by ``roadmap3d password FILE`` and read by ``roadmap3d app/demo --password-file FILE``
(:mod:`app.web.signin` checks a sign-in against it).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

#: A password file's first field, and scrypt's cost (16 MiB, ~50 ms per check).
PASSWORD_SCHEME = "scrypt"
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
#: Shortest password accepted when a password file is made (characters).
MIN_PASSWORD_CHARS = 12


@dataclass(frozen=True)
class PasswordHash:
    """A salted scrypt hash of the app's password, as a password file holds it: one line
    ``scrypt$N$r$p$SALT$HASH`` (salt and hash in base64). The password itself is kept nowhere."""

    n: int
    r: int
    p: int
    salt: bytes
    digest: bytes

    @classmethod
    def of(cls, password: str) -> PasswordHash:
        """A new hash of ``password`` (ValueError if shorter than MIN_PASSWORD_CHARS)."""
        if len(password) < MIN_PASSWORD_CHARS:
            raise ValueError(f"the password must be at least {MIN_PASSWORD_CHARS} characters")
        salt = secrets.token_bytes(16)
        digest = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P, dklen=32)
        return cls(SCRYPT_N, SCRYPT_R, SCRYPT_P, salt, digest)

    @classmethod
    def read(cls, path: str | os.PathLike[str]) -> PasswordHash:
        """The hash in a password file (ValueError naming the file and the problem)."""
        try:
            text = Path(path).read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"--password-file {path}: cannot read it ({exc})") from None
        fields = text.split("$")
        try:
            if len(fields) != 6 or fields[0] != PASSWORD_SCHEME:
                raise ValueError
            n, r, p = (int(f) for f in fields[1:4])
            salt, digest = base64.b64decode(fields[4], validate=True), base64.b64decode(fields[5], validate=True)
            if n < 2**10 or n & (n - 1) or not (1 <= r <= 64 and 1 <= p <= 16) or len(salt) < 8 or len(digest) < 16:
                raise ValueError
        except ValueError:
            raise ValueError(
                f"--password-file {path}: not a roadmap3d password file (make one with `roadmap3d password FILE`)"
            ) from None
        return cls(n, r, p, salt, digest)

    def text(self) -> str:
        """The password file's line."""
        b64 = lambda b: base64.b64encode(b).decode()  # noqa: E731
        return f"{PASSWORD_SCHEME}${self.n}${self.r}${self.p}${b64(self.salt)}${b64(self.digest)}"

    def verify(self, password: str) -> bool:
        """Whether ``password`` is the one hashed (constant time in the hash's comparison)."""
        if len(password) > 1024:
            return False
        found = hashlib.scrypt(password.encode(), salt=self.salt, n=self.n, r=self.r, p=self.p,
                               maxmem=256 * self.n * self.r + 2**20, dklen=len(self.digest))  # fmt: skip
        return hmac.compare_digest(found, self.digest)
