"""The NFFI source's config mistakes as ``fischer-gateway check-config`` reports them.

An operator who writes the C2 system's address with its subnet's prefix (``10.20.1.5/24``)
or a typo, or whose certificate is missing on the node, gets one line naming the key, its
line and what to write instead, not pydantic's internals.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import trustme


def check_config(path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "gateway", "check-config", *args, str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=dict(os.environ),
    )


def config_text(source: str) -> str:
    return (
        "gateway: {node_id: nffi-config}\n"
        "airframes: []\n"
        "sources:\n"
        "  - name: jas-relay\n"
        "    type: nffi\n" + source + "sinks: [{name: void, type: 'null'}]\n"
        "routes: [{sinks: [void]}]\n"
    )


def test_allow_list_mistakes_name_the_entry_and_say_what_to_write(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(
        config_text(
            "    uri: tcp://127.0.0.1:6500\n"
            "    allow: [10.20.1.5/24, 10.20.1.0/24, 10.20.1.300, 7, fe80::1/64, 10.20.1.7]\n"
        )
    )
    result = check_config(path, "--no-environment")
    assert result.returncode == 2
    out = result.stdout + result.stderr
    assert "lax-or-strict" not in out, out
    assert "IPv6" not in out, out
    where = f"{path.name}:7 sources[0].allow"
    assert f"{where}[0]: host bits set: write 10.20.1.0/24 for the network, or 10.20.1.5/32" in out
    assert f"{where}[2]: not an IP address or network" in out
    assert f"{where}[3]: expected an IP address or network as text" in out
    assert f"{where}[4]: host bits set: write fe80::/64 for the network, or fe80::1/128" in out
    assert "4 error(s)" in out, out


def test_a_missing_certificate_is_named_on_the_tls_section(tmp_path: Path) -> None:
    ca = trustme.CA()
    ca.cert_pem.write_to_path(str(tmp_path / "clients-ca.pem"))
    path = tmp_path / "config.yaml"
    path.write_text(
        config_text(
            "    uri: tls://127.0.0.1:6500\n"
            "    allow: [127.0.0.1/32]\n"
            "    tls:\n"
            f"      cert_file: {tmp_path / 'server.pem'}\n"
            f"      client_ca_file: {tmp_path / 'clients-ca.pem'}\n"
        )
    )
    assert check_config(path, "--no-environment").returncode == 0
    result = check_config(path)
    assert result.returncode == 2
    out = result.stdout + result.stderr
    assert f"{path.name}:8 sources[0].tls: {tmp_path / 'server.pem'}: No such file" in out, out
    assert "1 error(s)" in out
