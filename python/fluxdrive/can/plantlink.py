"""The power stage over the CAN bench bridge, as identification's `PlantLink`: each step
sends the duty answering the last sample and waits for the next one (the drive emulator --
the plant and the C drive core -- in lockstep in tests, the bench's MCU on a real bus).  The
duty acts two periods after its sample (written by the drive's next interrupt, applied from
the update event after it), one later than on the in-process link; the procedure reads what
was applied from the frames' duty fields."""

from __future__ import annotations

import copy
import time

import can
import numpy as np

from fluxdrive.can.bridge import BridgeConfig, CanBridge, bus_factory_from_params
from fluxdrive.can.emulator import DriveEmulator
from fluxdrive.can.loop import new_virtual_channel
from fluxdrive.core.machine import MachineCard
from fluxdrive.drive.identify import IdentifyAbort
from fluxdrive.drive.plant import FR_SEQ
from fluxdrive.drive.scenario import load_scenario, scenario_path
from fluxdrive.drive.sim import DriveSetup


class CanPlantLink:
    """PlantLink over python-can through `CanBridge`.  `emulate=True` starts the drive
    emulator (the simulated plant of `card` and the C drive core) on a virtual channel."""

    def __init__(
        self,
        card: MachineCard,
        channel: str | None = None,
        interface: str = "virtual",
        emulate: bool = True,
        max_s: float = 600.0,
        timeout_s: float = 60.0,
    ):
        self.ts_s = card.ts_s
        self.timeout_s = timeout_s
        ch = channel or new_virtual_channel("identify")
        self.emu = self.emu_bus = None
        if emulate:
            sc = copy.deepcopy(
                load_scenario(scenario_path("paper_2pct_150load"), overrides={"bench": {}})
            )
            sc.machine = card
            sc.load_profile_pu = np.array([[0.0, 0.0]])
            sc.duration_s = max_s
            self.emu_bus = can.Bus(
                interface="virtual", channel=ch, fd=True, receive_own_messages=False
            )
            self.emu = DriveEmulator(DriveSetup(sc), self.emu_bus, lockstep_wait_s=timeout_s)
        self.bridge = CanBridge(
            bus_factory_from_params(interface, ch, fd=True), BridgeConfig(stale_timeout_s=timeout_s)
        )
        self.bridge.connect()
        if self.emu is not None:
            self.emu.start(int(max_s / card.ts_s))
        self.seq = -1
        self._next(first_s=30.0)  # the drive is up
        ok, why = self.bridge.arm()
        for _ in range(200):  # PWM off until the drive reports itself armed
            if self.bridge.armed and self.bridge.mcu.get("sample_armed"):
                break
            self.step(np.full(3, 0.5), False)
        if not ok or not self.bridge.armed:
            raise IdentifyAbort(f"the drive did not arm: {why}")

    def _next(self, first_s: float | None = None) -> np.ndarray:
        t_end = time.monotonic() + (first_s or self.timeout_s)
        while time.monotonic() < t_end:
            self.bridge.tick()
            frames = self.bridge.poll(timeout=0.05, max_frames=1)
            if frames.shape[0]:
                fr = frames[-1]
                self.seq = int(fr[FR_SEQ])
                return fr.copy()
        raise IdentifyAbort(
            f"no sample from the drive within {self.timeout_s} s "
            f"({self.bridge.diagnostics().get('fault')})"
        )

    def step(self, duty: np.ndarray, enable: bool) -> np.ndarray:
        self.bridge.send_duty(self.seq, np.asarray(duty, dtype=float), bool(enable))
        return self._next()

    def pwm_off(self) -> None:
        try:
            self.step(np.full(3, 0.5), False)
        except IdentifyAbort:
            pass

    def close(self) -> None:
        self.pwm_off()
        self.bridge.disarm("identification done")
        if self.emu is not None:
            self.emu.stop()
        self.bridge.shutdown()
        if self.emu_bus is not None:
            self.emu_bus.shutdown()
