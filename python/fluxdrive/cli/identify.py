"""`./fluxdrive identify`: measure R, L, lambda, J, B and the deadtime voltage of a motor and
write a machine card that runs the scenarios directly.

  ./fluxdrive identify --machine CARD --out card.yaml   the simulated plant of CARD (sensor
                                                        noise and quantisation on); CARD also
                                                        gives the nameplate data
  ./fluxdrive identify --can --machine CARD --out c.yaml  the same over the CAN bench bridge
                                                        (drive emulator on a virtual bus)
  ./fluxdrive identify --check [--machine CARD ...]     accuracy on every shipped card (or
                                                        those named): table, last line JSON

Guards: --max-current-pu (abort, PWM off, above it) and --max-voltage-pu (standstill voltage
commands); --seed the simulated plant's noise (fluxdrive.drive.identify.IdentifySettings).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, fields
from pathlib import Path

from fluxdrive.core.machine import load_machine
from fluxdrive.core.schema import Parser, option
from fluxdrive.drive.identify import (
    TOLERANCE,
    IdentifyAbort,
    IdentifySettings,
    _stderr,
    errors,
    identify_sim,
)
from fluxdrive.drive.scenario import CONFIG_DIR, machine_path, save_machine


def _parser() -> argparse.ArgumentParser:
    ap = Parser(
        prog="fluxdrive identify",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument(
        "--machine",
        action="append",
        default=[],
        help="card of the simulated motor (name under config/machines or path); "
        "repeatable with --check",
    )
    ap.add_argument("--out", type=Path, help="write the identified machine card here")
    ap.add_argument(
        "--check",
        action="store_true",
        help="accuracy table over the shipped cards (or --machine ones)",
    )
    for f in fields(IdentifySettings):
        option(ap, "--" + f.name.replace("_", "-"), IdentifySettings)
    ap.add_argument(
        "--can",
        action="store_true",
        help="over the CAN bench bridge, to the drive emulator on a virtual bus "
        "(the same procedure; ~1 ms of wall time per PWM period)",
    )
    return ap


def main(argv: list[str]) -> int:
    args = _parser().parse_args(argv)
    settings = IdentifySettings(**{f.name: getattr(args, f.name) for f in fields(IdentifySettings)})
    if args.check:
        return _check(
            args.machine or sorted(p.stem for p in (CONFIG_DIR / "machines").glob("*.yaml")),
            settings,
        )
    card = load_machine(machine_path(args.machine[0] if args.machine else "default_spm"))
    t0 = time.perf_counter()
    try:
        ident = _identify(card, settings, args.can)
    except IdentifyAbort as exc:  # a guard tripped: PWM is off, the message says why
        print(f"fluxdrive identify: aborted: {exc}", file=sys.stderr)
        return 1
    out = args.out or Path(f"{card.name}_identified.yaml")
    save_machine(ident.card(card), out)
    print(
        f"identified in {time.perf_counter() - t0:.1f} s: R {ident.resistance_ohm:.4f} ohm, "
        f"L {ident.inductance_h * 1e3:.4f} mH, lambda {ident.flux_linkage_vs * 1e3:.4f} "
        f"mV s, J {ident.inertia_kgm2:.4g} kg m^2, B {ident.viscous_nms:.3g} N m s/rad, "
        f"deadtime {ident.deadtime_v:.3f} V per leg ({ident.deadtime_s * 1e6:.3f} us)"
    )
    print(f"card: {out}")
    return 0


def _identify(card, settings: IdentifySettings, can: bool):
    """The procedure on the simulated plant, or over the CAN bench bridge."""
    if not can:
        return identify_sim(card, progress=_stderr, settings=settings)[0]
    from fluxdrive.can.plantlink import CanPlantLink
    from fluxdrive.drive.identify import Identifier

    link = CanPlantLink(card)
    try:
        return Identifier(link, card, settings, progress=_stderr).run()
    finally:
        link.close()


def _check(cards: list[str], settings: IdentifySettings) -> int:
    keys = list(TOLERANCE)
    print(f"{'card':18s}" + "".join(f"{k + ' err':>11s}" for k in keys) + "   ok   wall")
    rows = {}
    t_all = time.perf_counter()
    for name in cards:
        card = load_machine(machine_path(name))
        t0 = time.perf_counter()
        ident, _ = identify_sim(card, settings=settings)
        e = errors(ident, card)
        ok = all(abs(e[k]) <= TOLERANCE[k] for k in keys)
        wall = time.perf_counter() - t0
        print(
            f"{card.name:18s}"
            + "".join(f"{e[k] * 100:+10.2f}%" for k in keys)
            + f"  {'yes' if ok else 'NO':>3s} {wall:5.1f} s",
            flush=True,
        )
        rows[card.name] = {
            "errors_pct": {k: round(e[k] * 100, 3) for k in keys},
            "ok": ok,
            "identified": asdict(ident),
            "wall_s": round(wall, 1),
        }
    print("tolerance: " + ", ".join(f"{k} {v * 100:g} %" for k, v in TOLERANCE.items()))
    print(
        json.dumps(
            {
                "benchmark": "identify",
                "tolerance_pct": {k: v * 100 for k, v in TOLERANCE.items()},
                "all_ok": all(r["ok"] for r in rows.values()),
                "cards": rows,
                "wall_s": round(time.perf_counter() - t_all, 1),
            }
        )
    )
    return 0 if all(r["ok"] for r in rows.values()) else 1
