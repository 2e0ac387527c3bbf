"""`focustrack bus secrets OUT`: the files of an authenticated Zenoh bus (docs/security.md).

Writes into OUT, with the openssl command:

- ``ca.pem``, a certificate authority made for this bus (its key is deleted once it has
  signed the router's certificate: nobody can sign another; run again to renew all);
- ``router.pem`` / ``router.key``, the router's TLS certificate for `--host` names;
- ``credentials.txt``, the router's password file: one random password per role;
- ``router.json5``: TLS, the password file and the access-control list of
  deploy/zenoh/acl.json5;
- ``instrument.json5``, ``focus.json5``, ``phase.json5``, ``scheduler.json5``,
  ``health.json5``: each role's Zenoh config (trust the CA, log in as that role), for
  ``--zenoh-config``;
- ``result.key``: the key the focus and phase services tag their results with and the scheduler
  checks them with (``--result-key-file``);
- ``frame.key``: the key the instrument tags its frames with and the focus service
  checks them with (``--frame-key-file``).

Paths inside the configs are where the services see OUT (`--mount`, e.g.
/run/focustrack in compose.secure.yaml; default OUT itself).

Only the two certificates are readable by all; the folder and every other file (keys,
passwords, the configs that hold them) are its owner's alone. `--owner UID` gives them
to the user the services run as: 10001 in every FocusTrack image, so the containers
can read what they mount (that needs root).

    sudo focustrack bus secrets deploy/secrets --host zenoh --mount /run/focustrack --owner 10001
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import secrets
import shutil
import subprocess
import sys
from pathlib import Path

import zenoh

from focustrack.arguments import user_id

ACL_FILE = Path(__file__).resolve().parents[1] / "deploy" / "zenoh" / "acl.json5"

#: The roles of the bus: each a user of the router's password file and a subject of its ACL.
ROLES = ("instrument", "focus", "phase", "scheduler", "health")

#: The shared keys of the tags (`focustrack_core.wire.trust`): results, frames.
KEY_FILES = ("result.key", "frame.key")


def openssl(folder: Path, *args: str) -> None:
    done = subprocess.run(["openssl", *args], cwd=folder, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {done.stderr.strip()}")


def make_certificates(folder: Path, hosts: list[str]) -> None:
    """A CA, and the router's certificate it signed for `hosts` (names or IP addresses)."""
    if shutil.which("openssl") is None:
        raise RuntimeError("the openssl command is needed to make the certificates")
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"IP:{h}" if _is_ip(h) else f"DNS:{h}" for h in hosts]
    (folder / "san.cnf").write_text(f"subjectAltName={','.join(names)}\n")
    key = ["-newkey", "rsa:2048", "-nodes"]
    openssl(folder, "req", "-x509", *key, "-days", "825", "-subj", "/CN=focustrack-bus-ca",
            "-keyout", "ca.key", "-out", "ca.pem")  # fmt: skip
    openssl(folder, "req", *key, "-subj", f"/CN={hosts[0]}", "-keyout", "router.key",
            "-out", "router.csr")  # fmt: skip
    openssl(folder, "x509", "-req", "-in", "router.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
            "-CAcreateserial", "-days", "825", "-extfile", "san.cnf",
            "-out", "router.pem")  # fmt: skip
    # The CA signs the router's certificate once; without its key nobody who can read
    # this folder (every container mounts it) can make another certificate it trusts.
    for scratch in ("router.csr", "san.cnf", "ca.srl", "ca.key"):
        (folder / scratch).unlink(missing_ok=True)


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
        return True
    except ValueError:
        return False


def client_config(ca: Path, user: str | None, password: str | None) -> dict:
    """A role's Zenoh config: trust `ca`; log in as `user` (None: no credentials)."""
    config: dict = {"transport": {"link": {"tls": {"root_ca_certificate": str(ca)}}}}
    if user is not None:
        config["transport"]["auth"] = {"usrpwd": {"user": user, "password": password}}
    return config


def router_config(mount: Path) -> dict:
    """The router's config: its certificate, the password file and our ACL."""
    acl = json.loads(zenoh.Config.from_file(str(ACL_FILE)).get_json("access_control"))
    return {
        "transport": {
            "link": {
                "tls": {
                    "listen_certificate": str(mount / "router.pem"),
                    "listen_private_key": str(mount / "router.key"),
                }
            },
            "auth": {"usrpwd": {"dictionary_file": str(mount / "credentials.txt")}},
        },
        "access_control": acl,
    }


def write_bus_files(
    folder: Path,
    hosts: list[str],
    mount: Path | None = None,
    extra_users: dict[str, str] | None = None,
) -> dict[str, str]:
    """Every file of the bus in `folder` (see the module's doc); the passwords by user.

    `extra_users` are added to the password file as they are (a test's intruder).
    """
    mount = folder if mount is None else mount
    make_certificates(folder, hosts)
    passwords = {role: secrets.token_urlsafe(18) for role in ROLES} | (extra_users or {})
    (folder / "credentials.txt").write_text(
        "".join(f"{user}:{password}\n" for user, password in passwords.items())
    )
    (folder / "router.json5").write_text(json.dumps(router_config(mount), indent=2) + "\n")
    for role in ROLES:
        config = client_config(mount / "ca.pem", role, passwords[role])
        (folder / f"{role}.json5").write_text(json.dumps(config, indent=2) + "\n")
    for key in KEY_FILES:
        (folder / key).write_text(secrets.token_hex(32) + "\n")
    return passwords


#: The files anyone may read: certificates, no secret in them.
PUBLIC_FILES = ("ca.pem", "router.pem")


def restrict(folder: Path, owner: int | None) -> None:
    """The folder and its secret files for their owner alone (`PUBLIC_FILES` for all);
    given to user `owner` first where set (PermissionError without root)."""
    paths = [folder, *sorted(folder.iterdir())]
    if owner is not None:
        for path in paths:
            os.chown(path, owner, owner)
    folder.chmod(0o700)
    for path in paths[1:]:
        path.chmod(0o644 if path.name in PUBLIC_FILES else 0o600)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out", type=Path, help="folder to write the files into")
    parser.add_argument(
        "--host",
        action="append",
        help="a name or address of the router in its certificate (repeatable; default zenoh)",
    )
    parser.add_argument(
        "--mount", type=Path, help="where the services see the folder (default: the folder)"
    )
    parser.add_argument(
        "--owner",
        type=user_id,  # a negative one was a traceback, with half the files written
        metavar="UID",
        help="give the files to this user (and group): the services' own, 10001 in the "
        "FocusTrack images; needs root (default: whoever runs the command)",
    )


def run(args: argparse.Namespace) -> int:
    try:
        write_bus_files(args.out, args.host or ["zenoh"], args.mount)
        restrict(args.out, args.owner)
    except PermissionError as error:
        print(
            f"focustrack bus secrets: error: {error}: giving the files to uid {args.owner} "
            f"needs root (sudo), or `chown -R {args.owner} {args.out}` afterwards",
            file=sys.stderr,
        )
        return 1
    except (RuntimeError, OSError) as error:
        print(f"focustrack bus secrets: error: {error}", file=sys.stderr)
        return 1
    owner = "you" if args.owner is None else f"uid {args.owner}"
    print(f"wrote the bus's certificates, passwords and configs to {args.out}, for {owner} only")
    if args.owner is None:
        print("containers read it as uid 10001: give it to them with --owner 10001 (as root)")
    return 0
