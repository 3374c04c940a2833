"""Files shipped in the wheel for installing without the source tree.

The example config, the systemd unit and the operator documentation live in the repository
(``config/``, ``deploy/``, ``docs/``); ``gateway/data/share`` holds symbolic links to them, and
the wheel carries their contents. ``fischer-gateway files`` lists, prints or writes them, so
deploy/INSTALL.md works the same from a wheel as from a checkout.

``files --out DIR`` writes them side by side in one directory, so a document's relative
links are rewritten as it is written (``shipped_text``): a link to another shipped file
points at its copy in DIR; a link into the source tree (a schema, a module) is no link
there, so it becomes its text followed by the path in the source tree.
"""

from __future__ import annotations

import posixpath
import re
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import TextIO

__all__ = [
    "DESCRIPTIONS",
    "ORIGINS",
    "files_command",
    "read_shared",
    "shared_names",
    "shipped_text",
    "write_shared",
]

#: Every shipped file and what it is.
DESCRIPTIONS = {
    "example.yaml": "the example config, commented (copy to /etc/fischer-gateway/config.yaml)",
    "fischer-gateway.service": "the hardened systemd unit (copy to /etc/systemd/system/)",
    "INSTALL.md": "installing on a Debian 12 node as a service",
    "operations.md": "running it: reload, logs, metrics and alerts, health endpoints",
    "architecture.md": "how the gateway is built, with a diagram",
    "writing-a-sink.md": "the sink contract, an example sink and its contract check",
    "events.md": "every event kind and field, generated from the event models",
    "tunnel.md": "the AES-256-GCM airframe tunnel",
    "durability.md": "durable delivery: the spool, detection acknowledgements, dead letters",
    "detection-ack.md": "FISCHER_DETECTION_ACK: what an airframe must do to lose no detection",
    "cot.md": "the CoT sink and source: symbols, stale times, UDP and TAK server streams, TAK v1",
    "slb.md": "the SLB sink and order source: endpoints, JC3IEDM payload, options",
    "nffi.md": "the NFFI sink and source: mapping, IP1 framing, trust, options",
    "sweccis.md": "the SWECCIS sink and order source: FAS documents, framing, XSD, options",
    "ra180.md": "the Ra 180 sink: the 127-character message, budget, serial/UDP, Swedish voice",
    "security.md": "threat model per link mode and port, the passthrough policy, the attack tests",
    "counter-uas.md": "fusion into tracks, the counter-UAS cue and the GUTE II sink",
    "hopping.md": "AD9361 hop plans: checks, upload, acknowledgement, hop events",
    "klv.md": "STANAG 4609 / MISB ST 0601 KLV metadata over UDP and MPEG-TS",
    "map.md": "the live map page and its change stream: JSON, options, security",
    "orders.md": "five-line orders to the airframes: checks, missions, statuses",
    "scale-out.md": "several nodes, one picture: NATS JetStream between gateway nodes",
    "tracking.md": "scoring tracks against ground truth: truth files, GOSPA, the scenarios",
    "README.md": "what works today",
}


#: The repository folder of each shipped file that is not in ``docs/``.
ORIGINS = {
    "README.md": "",
    "INSTALL.md": "deploy",
    "fischer-gateway.service": "deploy",
    "example.yaml": "config",
}
#: A markdown link or image (``!``): its text, its target and an optional #anchor (a bare
#: #anchor is no match).
_LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)#\s]+)(#[^)\s]*)?\)")


def _origin(name: str) -> str:
    return posixpath.join(ORIGINS.get(name, "docs"), name)


def _share() -> Traversable:
    return files("gateway").joinpath("data/share")


def shared_names() -> list[str]:
    """The names of the shipped files, in ``DESCRIPTIONS`` order."""
    return list(DESCRIPTIONS)


def read_shared(name: str) -> str:
    """The text of one shipped file; ``KeyError`` naming the known ones for anything else."""
    if name not in DESCRIPTIONS:
        raise KeyError(f"no shipped file {name!r}; expected one of {', '.join(DESCRIPTIONS)}")
    return _share().joinpath(name).read_text(encoding="utf-8")


def shipped_text(name: str) -> str:
    """The text of one shipped file as ``files --out`` writes it (module docstring)."""
    text = read_shared(name)
    if not name.endswith(".md"):
        return text
    shipped = {_origin(known): known for known in DESCRIPTIONS}
    folder = posixpath.dirname(_origin(name))

    def relink(match: re.Match[str]) -> str:
        image, label, target, anchor = match[1], match[2], match[3], match[4] or ""
        if re.match(r"[a-z][a-z0-9+.-]*:", target):
            return match[0]  # the web, mail
        path = posixpath.normpath(posixpath.join(folder, target))
        if path in shipped:
            return f"{image}[{label}]({shipped[path]}{anchor})"
        if image:  # a picture the share does not hold: say where it is
            return f"{label} (picture: `{path}` in the source tree)"
        return label if path.strip("/") in label else f"{label} (`{path}` in the source tree)"

    return _LINK.sub(relink, text)


def write_shared(directory: Path) -> list[Path]:
    """Write every shipped file into ``directory`` (created, files replaced); the paths."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name in DESCRIPTIONS:
        target = directory / name
        target.write_text(shipped_text(name), encoding="utf-8")
        target.chmod(0o644)
        written.append(target)
    return written


def files_command(name: str | None, out_dir: Path | None, out: TextIO, err: TextIO) -> int:
    """``fischer-gateway files [NAME] [--out DIR]``: list, print one, or write all; exit code.

    Exit 2 for an unknown name.
    """
    if out_dir is not None:
        for path in write_shared(out_dir):
            print(f"wrote {path}", file=out)
        return 0
    if name is None:
        for known, what in DESCRIPTIONS.items():
            print(f"{known:<24} {what}", file=out)
        return 0
    try:
        out.write(read_shared(name))
    except KeyError as exc:
        print(exc.args[0], file=err)
        return 2
    return 0
