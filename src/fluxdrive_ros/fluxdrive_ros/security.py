"""ROS 2 security (SROS2) with the pip wheels: clear errors, and a keystore made with openssl.

What the installed middleware does (measured; details in docs/safety.md):
- rcl reads ROS_SECURITY_ENABLE / ROS_SECURITY_STRATEGY / ROS_SECURITY_KEYSTORE /
  ROS_SECURITY_ENCLAVE_OVERRIDE (or `--ros-args --enclave`).  With Enforce and no enclave
  directory, rclpy.init fails ("SECURITY ERROR: directory '<keystore>/enclaves' does not
  exist"); with Permissive it runs the node unsecured.
- When the enclave is found, rmw_fastrtps_cpp asks Fast DDS for the DDS-Security plugins,
  and the Fast DDS of these wheels is built without them ("This Fast DDS version doesn't
  have the security libraries"): a secured node cannot be created here, in either strategy.
  With a Fast DDS built with -DSECURITY=ON (ROS 2 binary packages) the same keystore and
  environment give authenticated, encrypted, access-controlled topics.
- There is no `ros2 security` command (no ros2cli/sros2 in the wheels), so
  `python -m fluxdrive_ros.security keystore DIR` writes an SROS2-layout keystore with the
  openssl command line: one self-signed CA (identity and permissions), the signed
  governance, and per enclave a key, a certificate and signed permissions that allow every
  topic on every domain (tighten permissions.xml and re-sign for real use).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from fluxdrive.core.schema import Parser

_GOVERNANCE = """<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
     xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_governance.xsd">
  <domain_access_rules>
    <domain_rule>
      <domains><id_range><min>0</min><max>232</max></id_range></domains>
      <allow_unauthenticated_participants>false</allow_unauthenticated_participants>
      <enable_join_access_control>true</enable_join_access_control>
      <discovery_protection_kind>ENCRYPT</discovery_protection_kind>
      <liveliness_protection_kind>ENCRYPT</liveliness_protection_kind>
      <rtps_protection_kind>SIGN</rtps_protection_kind>
      <topic_access_rules>
        <topic_rule>
          <topic_expression>*</topic_expression>
          <enable_discovery_protection>true</enable_discovery_protection>
          <enable_liveliness_protection>true</enable_liveliness_protection>
          <enable_read_access_control>true</enable_read_access_control>
          <enable_write_access_control>true</enable_write_access_control>
          <metadata_protection_kind>ENCRYPT</metadata_protection_kind>
          <data_protection_kind>ENCRYPT</data_protection_kind>
        </topic_rule>
      </topic_access_rules>
    </domain_rule>
  </domain_access_rules>
</dds>
"""

_PERMISSIONS = """<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
     xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_permissions.xsd">
  <permissions>
    <grant name="{enclave}">
      <subject_name>CN={cn}</subject_name>
      <validity><not_before>2020-01-01T00:00:00</not_before><not_after>2040-01-01T00:00:00</not_after></validity>
      <allow_rule>
        <domains><id_range><min>0</min><max>232</max></id_range></domains>
        <publish><topics><topic>*</topic></topics></publish>
        <subscribe><topics><topic>*</topic></topics></subscribe>
      </allow_rule>
      <default>DENY</default>
    </grant>
  </permissions>
</dds>
"""


def precheck() -> str | None:
    """One line if ROS 2 security is enforced without a keystore (rcl would fail
    with "failed to initialize rcl: error not set" and a traceback), else None.  Called by
    every fluxdrive entry point before rclpy.init."""
    if os.environ.get("ROS_SECURITY_ENABLE", "").lower() != "true":
        return None
    strategy = os.environ.get("ROS_SECURITY_STRATEGY", "Permissive")
    if strategy != "Enforce":
        return None
    if os.environ.get("ROS_SECURITY_KEYSTORE", ""):  # (a wrong one: rcl says which file)
        return None
    return (
        "ROS 2 security is enforced (ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY="
        "Enforce) but ROS_SECURITY_KEYSTORE is not set: create a keystore with "
        "`python -m fluxdrive_ros.security keystore DIR` and set "
        "ROS_SECURITY_KEYSTORE=DIR, or unset ROS_SECURITY_ENABLE"
    )


def describe_error(exc: BaseException) -> str | None:
    """A one-line explanation of a security failure of rclpy.init / node creation, or
    None if `exc` is not about security."""
    text = str(exc)
    clean = re.sub(r",? at /\S+:\d+", "", text).replace("\n", " ").strip()
    ks = os.environ.get("ROS_SECURITY_KEYSTORE", "(ROS_SECURITY_KEYSTORE not set)")
    if "security libraries" in text:
        return (
            f"ROS 2 security is on (ROS_SECURITY_ENABLE=true, enclave found in {ks}) but "
            f"the installed Fast DDS is built without DDS-Security, so a secured node "
            f"cannot run here; unset ROS_SECURITY_ENABLE or use a Fast DDS built with "
            f"SECURITY=ON (docs/safety.md)"
        )
    if "SECURITY ERROR" in text:
        detail = clean.split("SECURITY ERROR:", 1)[1].strip()
        strategy = os.environ.get("ROS_SECURITY_STRATEGY", "Permissive")
        return (
            f"ROS 2 security is on (ROS_SECURITY_ENABLE=true, ROS_SECURITY_STRATEGY="
            f"{strategy}) and the keystore is not usable: {detail} -- create it with "
            f"`python -m fluxdrive_ros.security keystore {ks}` or unset ROS_SECURITY_ENABLE"
        )
    return None


def _openssl(*args: str, cwd: Path) -> None:
    r = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {r.stderr.strip().splitlines()[-1]}")


def loopback_tls_pair(days: int = 2) -> tuple[bytes, bytes]:
    """(certificate, PKCS#8 key) PEM of a self-signed P-256 certificate for 127.0.0.1, made in
    a private temporary folder that is removed at once (the Foxglove bridge's inner server:
    fluxdrive_bringup.view.gate)."""
    import tempfile

    if shutil.which("openssl") is None:
        raise RuntimeError("the openssl command is needed for the bridge's inner TLS link")
    with tempfile.TemporaryDirectory(prefix="fluxdrive-tls-") as tmp:
        d = Path(tmp)  # mode 0700: the key is never readable by others
        _openssl(
            "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
            "-nodes", "-keyout", "key.pem", "-out", "cert.pem", "-days", str(days),
            "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
            cwd=d,
        )  # fmt: skip
        return (d / "cert.pem").read_bytes(), (d / "key.pem").read_bytes()


def make_keystore(root: Path, enclaves: list[str], days: int = 3650) -> list[Path]:
    """Write an SROS2-layout keystore under `root` (created if needed; an existing CA is
    reused) with the given enclaves (e.g. "/fluxdrive").  Returns the enclave directories."""
    if shutil.which("openssl") is None:
        raise RuntimeError("the openssl command is needed to make a keystore")
    root = Path(root)
    for sub in ("public", "private", "enclaves"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    ca_key, ca_cert = root / "private" / "ca.key.pem", root / "public" / "ca.cert.pem"
    if not ca_key.exists():
        _make_ca(root, ca_key, ca_cert, days)
    gov = root / "enclaves" / "governance.xml"
    gov.write_text(_GOVERNANCE)
    _sign(str(gov), str(gov.with_suffix(".p7s")), ca_key, ca_cert, cwd=root)
    return [
        _make_enclave(root, e, ca_key, ca_cert, gov.with_suffix(".p7s"), days) for e in enclaves
    ]


def _make_ca(root: Path, ca_key: Path, ca_cert: Path, days: int) -> None:
    """One self-signed CA, used as both the identity and the permissions CA."""
    _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", str(ca_key), cwd=root)
    _openssl(
        "req",
        "-new",
        "-x509",
        "-key",
        str(ca_key),
        "-out",
        str(ca_cert),
        "-days",
        str(days),
        "-subj",
        "/CN=fluxdrive_keystore_ca",
        "-addext",
        "basicConstraints=critical,CA:true",
        "-addext",
        "keyUsage=keyCertSign,cRLSign",
        cwd=root,
    )
    for name in ("identity_ca.cert.pem", "permissions_ca.cert.pem"):
        shutil.copy(ca_cert, root / "public" / name)
    for name in ("identity_ca.key.pem", "permissions_ca.key.pem"):
        shutil.copy(ca_key, root / "private" / name)


def _sign(doc: str, out: str, ca_key: Path, ca_cert: Path, cwd: Path) -> None:
    """An S/MIME signature of a governance or permissions document by the CA."""
    _openssl(
        "smime",
        "-sign",
        "-in",
        doc,
        "-text",
        "-out",
        out,
        "-signer",
        str(ca_cert),
        "-inkey",
        str(ca_key),
        cwd=cwd,
    )


def _make_enclave(
    root: Path, enclave: str, ca_key: Path, ca_cert: Path, gov_p7s: Path, days: int
) -> Path:
    """An enclave's key, certificate (signed by the CA), permissions and the CA files."""
    if not enclave.startswith("/") or "//" in enclave:
        raise ValueError(f"enclave {enclave!r}: an absolute name like /fluxdrive/drive")
    d = root / "enclaves" / enclave.strip("/")
    d.mkdir(parents=True, exist_ok=True)
    cn = enclave.strip("/").replace("/", ".") or "root"
    _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", "key.pem", cwd=d)
    _openssl("req", "-new", "-key", "key.pem", "-out", "req.csr", "-subj", f"/CN={cn}", cwd=d)
    _openssl(
        "x509",
        "-req",
        "-in",
        "req.csr",
        "-CA",
        str(ca_cert),
        "-CAkey",
        str(ca_key),
        "-CAcreateserial",
        "-out",
        "cert.pem",
        "-days",
        str(days),
        cwd=d,
    )
    (d / "req.csr").unlink()
    (d / "permissions.xml").write_text(_PERMISSIONS.format(enclave=enclave, cn=cn))
    _sign("permissions.xml", "permissions.p7s", ca_key, ca_cert, cwd=d)
    shutil.copy(gov_p7s, d / "governance.p7s")
    shutil.copy(ca_cert, d / "identity_ca.cert.pem")
    shutil.copy(ca_cert, d / "permissions_ca.cert.pem")
    return d


def main(argv: list[str] | None = None) -> int:
    ap = Parser(
        prog="python -m fluxdrive_ros.security",
        description="SROS2 keystore for the fluxdrive graph (openssl)",
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    k = sub.add_parser("keystore", help="create a keystore (or add enclaves to one)")
    k.add_argument("dir", type=Path)
    k.add_argument(
        "--enclave",
        action="append",
        default=[],
        help="enclave name, repeatable (default /fluxdrive)",
    )
    args = ap.parse_args(argv)
    try:
        dirs = make_keystore(args.dir, args.enclave or ["/fluxdrive"])
    except (RuntimeError, ValueError, OSError) as exc:
        print(f"keystore: {exc}", file=sys.stderr)
        return 2
    for d in dirs:
        print(f"enclave {d}")
    print(
        f"use: ROS_SECURITY_ENABLE=true ROS_SECURITY_STRATEGY=Enforce "
        f"ROS_SECURITY_KEYSTORE={args.dir.resolve()} "
        f"ROS_SECURITY_ENCLAVE_OVERRIDE={args.enclave[0] if args.enclave else '/fluxdrive'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
