"""Killing a writer process in the middle of a write, for the crash-safety tests."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).parent


def kill_mid_write(script: str, target: Path) -> None:
    """Run ``script`` (which writes ``target``) and SIGKILL it once its temporary file
    holds more than 2 MB.

    ``script`` is formatted with ``tests`` (this directory, for its imports) and
    ``target``; it prints "writing" when it starts writing.
    """
    code = script.format(tests=str(TESTS), target=str(target))
    process = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    partial = None
    try:
        if process.stdout.readline().strip() != "writing":
            process.wait(timeout=60)
            pytest.fail(f"the writer did not start: {process.stderr.read()[-2000:]}")
        deadline = time.monotonic() + 60
        while partial is None and time.monotonic() < deadline and process.poll() is None:
            for temporary in target.parent.glob(f".{target.name}.tmp-*"):
                if temporary.exists() and temporary.stat().st_size > 2_000_000:
                    partial = temporary
            time.sleep(0.002)
        process.send_signal(signal.SIGKILL)
    finally:
        process.kill()
        process.wait()
    assert partial is not None, "the writer finished before it could be interrupted"
