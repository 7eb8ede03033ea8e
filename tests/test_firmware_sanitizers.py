"""The C unit tests of the drive core (firmware/tests/test_core.c: fault injection per
protection, saturated ADC, 0 V and NaN bus, reference age and order, counter wraps, ...)
built a second time with AddressSanitizer and UndefinedBehaviorSanitizer, every finding
fatal (-fno-sanitize-recover=all): a float->unsigned conversion of a NaN duty, a signed
overflow in a counter or an out-of-bounds frame copy fails the test. No ROS."""

from __future__ import annotations

import subprocess
import sys

from fluxdrive.can import firmware as fw

SANITIZE = "-fsanitize=address,undefined -fno-sanitize-recover=all -fno-omit-frame-pointer"


def test_c_unit_tests_pass_under_asan_and_ubsan(tmp_path):
    bdir = tmp_path / "sanitized"
    configure = [
        "cmake", "-S", str(fw.FIRMWARE_DIR), "-B", str(bdir), f"-DFD_PYTHON={sys.executable}",
        "-DCMAKE_BUILD_TYPE=Debug", f"-DCMAKE_C_FLAGS={SANITIZE}",
    ]  # fmt: skip
    for cmd in (configure, ["cmake", "--build", str(bdir), "-j", "2", "--target", "fd_core_test"]):
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    r = subprocess.run(
        ["ctest", "--test-dir", str(bdir), "--output-on-failure"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    print(r.stdout[-2000:])
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert "all checks passed" in r.stdout or "100% tests passed" in r.stdout
