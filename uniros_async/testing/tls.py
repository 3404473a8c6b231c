"""Throw-away certificates for ``tls://`` in tests and benchmarks, made with the ``openssl`` command.

``write_test_certs(directory)`` writes a CA and one certificate it signed, valid for ``localhost`` and 127.0.0.1
and usable by either end (serverAuth and clientAuth), with P-256 keys. Never use them beyond a test: the key files
are written without a passphrase.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
from pathlib import Path

from uniros_async.errors import ConfigError
from uniros_async.transports.base import TransportOptions

__all__ = ["TlsFiles", "write_test_certs"]

_DAYS = "2"
_KEY = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class TlsFiles:
    """Paths of a test CA and a certificate it signed."""

    ca_file: str
    cert_file: str
    key_file: str

    def options(self, base: TransportOptions | None = None) -> TransportOptions:
        """``base`` (default TransportOptions()) with these files."""
        return dataclasses.replace(
            base or TransportOptions(),
            tls_cert_file=self.cert_file,
            tls_key_file=self.key_file,
            tls_ca_file=self.ca_file,
        )

    def environ(self) -> dict[str, str]:
        """The same files as the ``UNIROS_TLS_*`` variables ``tls://`` falls back to."""
        return {"UNIROS_TLS_CERT": self.cert_file, "UNIROS_TLS_KEY": self.key_file, "UNIROS_TLS_CA": self.ca_file}


def _openssl(*args: str, cwd: Path) -> None:
    proc = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    if proc.returncode:
        raise ConfigError(f"openssl {' '.join(args[:2])} failed: {proc.stderr.strip()}")


def write_test_certs(directory: str | os.PathLike[str], *, name: str = "peer") -> TlsFiles:
    """Write ``ca.pem``/``ca.key`` (unless present) and ``NAME.pem``/``NAME.key`` signed by that CA.

    Raises:
        ConfigError: the ``openssl`` command is missing or failed.
    """
    if shutil.which("openssl") is None:
        raise ConfigError("the openssl command is needed to write test certificates (Debian: apt-get install openssl)")
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    if not (d / "ca.pem").exists():
        _openssl(
            "req", "-x509", *_KEY, "-keyout", "ca.key", "-out", "ca.pem", "-days", _DAYS,
            "-subj", "/CN=uniros test CA",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
            cwd=d,
        )  # fmt: skip
    ext = d / f"{name}.ext"
    ext.write_text(
        "subjectAltName=DNS:localhost,IP:127.0.0.1,IP:::1\n"
        "basicConstraints=CA:FALSE\n"
        "keyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=serverAuth,clientAuth\n"
    )
    _openssl("req", *_KEY, "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
    _openssl(
        "x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
        "-out", f"{name}.pem", "-days", _DAYS, "-extfile", ext.name,
        cwd=d,
    )  # fmt: skip
    return TlsFiles(ca_file=str(d / "ca.pem"), cert_file=str(d / f"{name}.pem"), key_file=str(d / f"{name}.key"))
