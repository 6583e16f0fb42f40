"""Logging in to the fake RWS controller as ABB's controllers ask for it: HTTP Digest (RFC 7616,
MD5, qop=auth, realm ``validusers@robapi.abb``) on RWS 1.0, Basic (RFC 7617) over HTTPS on RWS
2.0; and the self-signed certificate of its HTTPS (made with the ``openssl`` tool)."""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import re
import secrets
import ssl
import subprocess
from pathlib import Path

__all__ = ["REALM", "Login", "tls_context", "write_credentials"]

REALM = "validusers@robapi.abb"
_FIELD = re.compile(r'(\w+)=(?:"([^"]*)"|([^,\s]*))')


class Login:
    """One user's credentials and the digest nonces handed out (``forget`` on a restart)."""

    def __init__(self, version: int, user: str, password: str) -> None:
        self.version, self.user, self._password = version, user, password
        self._nonces: set[str] = set()

    def forget(self) -> None:
        self._nonces.clear()

    def challenge(self, stale: bool = False) -> str:
        """The ``WWW-Authenticate`` of a 401."""
        if self.version == 2:
            return f'Basic realm="{REALM}"'
        nonce = secrets.token_hex(16)
        self._nonces.add(nonce)
        return (f'Digest realm="{REALM}", qop="auth", nonce="{nonce}", '
                f'opaque="{secrets.token_hex(8)}", algorithm=MD5'
                + (", stale=TRUE" if stale else ""))

    def check(self, header: str, method: str, raw_path: str) -> bool | None:
        """True/False for a checked ``Authorization``, None for a digest on a nonce this
        controller did not hand out (answered with a fresh challenge, ``stale``)."""
        scheme, _, rest = header.partition(" ")
        if self.version == 2 and scheme == "Basic":
            try:
                user, _, pw = base64.b64decode(rest).decode().partition(":")
            except (ValueError, UnicodeDecodeError):
                return False
            return user == self.user and hmac.compare_digest(pw, self._password)
        if self.version == 1 and scheme == "Digest":
            f = {m.group(1): m.group(2) if m.group(2) is not None else m.group(3)
                 for m in _FIELD.finditer(rest)}
            if f.get("nonce") not in self._nonces:
                return None

            def md5(text: str) -> str:
                return hashlib.md5(text.encode()).hexdigest()  # RFC 7616 algorithm=MD5

            ha1 = md5(f"{self.user}:{REALM}:{self._password}")
            ha2 = md5(f"{method}:{f.get('uri', '')}")
            want = md5(f"{ha1}:{f['nonce']}:{f.get('nc', '')}:{f.get('cnonce', '')}:"
                       f"{f.get('qop', '')}:{ha2}")
            return (f.get("username") == self.user and f.get("uri") == raw_path
                    and hmac.compare_digest(want, f.get("response", "")))
        return False


def tls_context(workdir: Path) -> ssl.SSLContext:
    """A server context with a self-signed certificate for 127.0.0.1 (``rws-cert.pem``, the
    daemon's ``ca_file``), made once per workdir."""
    cert, key = workdir / "rws-cert.pem", workdir / "rws-key.pem"
    if not cert.exists():
        subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt",
                        "ec_paramgen_curve:prime256v1", "-nodes", "-keyout", str(key),
                        "-out", str(cert), "-days", "2", "-subj", "/CN=127.0.0.1",
                        "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost"],
                       check=True, capture_output=True, timeout=60)
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.load_cert_chain(cert, key)
    return ctx


def write_credentials(path: Path, user: str, password: str) -> None:
    """The daemon's credentials file, ``user:password``, created owner-only (mode 0600)."""
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"{user}:{password}\n")
