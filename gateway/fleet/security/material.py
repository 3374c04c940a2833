"""The gateway's security material, built once from config: tunnel opener, sealers, verifiers.

The gateway holds the master key (from a 0600 file or a systemd credential) and derives
every airframe's day keys from it; airframes hold only their own day keys.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from gateway.clock import Clock
from gateway.config import Config
from gateway.errors import ConfigError, ConfigIssue
from gateway.fleet.deframe import frame_for_stream
from gateway.fleet.mavlink import crc_extra, split_frames
from gateway.fleet.security.keys import read_credential, read_key_file
from gateway.fleet.security.signing import OutboundSigner, SigningVerifier
from gateway.fleet.security.tunnel import DayKeys, Sealer, TunnelOpener

__all__ = ["Security"]


@dataclass
class Security:
    """Tunnel opener and sealers, MAVLink signing verifiers by sysid and signers by airframe."""

    opener: TunnelOpener | None = None
    sealers: dict[str, Sealer] = field(default_factory=dict)
    verifiers: dict[int, SigningVerifier] = field(default_factory=dict)
    signers: dict[str, OutboundSigner] = field(default_factory=dict)

    @classmethod
    def from_config(cls, config: Config, clock: Clock) -> Security:
        """Read the keys the config names; raise ``ConfigError`` naming a bad key file."""
        tunnelled = [
            a for a in config.airframes if any(link.security == "tunnel" for link in a.links)
        ]
        security = cls()
        if tunnelled:
            tunnel = config.tunnel
            if tunnel.master_key_file is not None:
                master = read_key_file(tunnel.master_key_file)
            elif tunnel.master_key_credential is not None:
                master = read_credential(tunnel.master_key_credential)
            else:
                raise ConfigError(
                    [
                        ConfigIssue(
                            "(config)",
                            None,
                            "tunnel",
                            "a tunnel link needs master_key_file or master_key_credential",
                        )
                    ]
                )
            keys = DayKeys(master=master)
            max_frame = max(link.max_frame_bytes for a in tunnelled for link in a.links)
            security.opener = TunnelOpener(
                keys,
                frozenset(a.id for a in tunnelled),
                clock,
                grace_s=tunnel.grace_s,
                skew_s=tunnel.skew_s,
                freshness_s=tunnel.freshness_s,
                max_frame_bytes=max_frame,
                # Redundant copies on two links arrive within the de-duplication window.
                cross_link_s=max(a.dedup_window_s for a in tunnelled),
            )
            security.sealers = {a.id: Sealer(a.id, keys, clock) for a in tunnelled}
        for airframe in config.airframes:
            if airframe.signing is not None:
                signing = airframe.signing
                key = read_key_file(signing.key_file, exact=True)
                security.verifiers[airframe.sysid] = SigningVerifier(
                    key,
                    require_signed=signing.require_signed,
                    clock=time.time,
                    accept_unsigned_msgids=frozenset(signing.accept_unsigned_msgids),
                )
                security.signers[airframe.id] = OutboundSigner(
                    key, crc_extra=crc_extra, clock=time.time
                )
        return security

    def sign(self, airframe: str, frames: bytes) -> bytes:
        """Sign every MAVLink 2 frame in ``frames`` for ``airframe``; raise ``FrameError``.

        Refuses (``Malformed``) MAVLink 1 frames, unknown message ids and trailing bytes:
        nothing goes out on a signed link unsigned.
        """
        signer = self.signers[airframe]
        return b"".join(signer.sign(frame) for frame in split_frames(frames))

    def seal(self, airframe: str, frames: bytes, *, stream: bool) -> bytes:
        """Seal outbound MAVLink ``frames`` for ``airframe`` (length-prefixed on streams)."""
        sealed = self.sealers[airframe].seal(frames)
        return frame_for_stream(sealed) if stream else sealed
