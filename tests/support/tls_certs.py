"""A certificate authority and one certificate per name, made with the openssl command, for the
tests that run mutual TLS on loopback (subjectAltName localhost and 127.0.0.1)."""
from __future__ import annotations

import subprocess
from pathlib import Path


def make_certs(d: Path, names: dict[str, str]) -> Path:
    """`names`: file stem -> common name. Writes ca.pem and <stem>.pem/.key in `d`; returns `d`."""
    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
        "-subj", "/CN=cobot-dt test CA")
    for stem, cn in names.items():
        (d / f"{stem}.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                                       "extendedKeyUsage=serverAuth,clientAuth\n")
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{stem}.key", "-out", f"{stem}.csr",
            "-subj", f"/CN={cn}")
        run("x509", "-req", "-in", f"{stem}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{stem}.pem", "-days", "2", "-extfile", f"{stem}.ext")
    return d
