"""The main process's resident memory during a streamed patch build, moment by moment.

What ``cellcoadd build`` does (headers read, :func:`~cellcoadd.builder.stream_patch`,
:func:`~cellcoadd.io.api.write_cells`) on :mod:`bench_pool`'s realistic patch, in this
process, with a thread sampling this process's ``VmRSS`` (Linux ``/proc/self/status``) every
0.1 s. Prints the RSS after the imports, after the set-up (``stream_patch`` returned) and
every ``--every`` cells handed to the writer (default: one block of the realistic patch on
2 workers, 44 cells), then the sampled and ``ru_maxrss`` peaks. Where memory grows block
after block, something keeps the cells written (a pool that held its futures did: 1234 MB
against 612 MB once fixed, docs/performance.md).

Run as ``PYTHONPATH=. .venv/bin/python benchmarks/trace_build_memory.py --workdir
/tmp/pool-inputs [--workers 2 | --scheduler tcp://...]``; the inputs are bench_pool's
(written there if missing). One build: about 25 CPU s on the realistic patch.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import resource  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402

from bench_pool import write_inputs  # noqa: E402
from common import format_table, machine_summary  # noqa: E402

from cellcoadd.model.cell_coadd import CellCoadd  # noqa: E402


def rss_mb() -> float:
    """This process's resident set size now, MB (``VmRSS``)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


class Sampler:
    """Samples :func:`rss_mb` every ``interval`` s in a daemon thread; ``peak`` is the
    largest sample."""

    def __init__(self, interval: float = 0.1) -> None:
        self.peak = rss_mb()
        self._stop = threading.Event()
        self._interval = interval
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._interval):
            self.peak = max(self.peak, rss_mb())

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", required=True, help="bench_pool's inputs (made if missing)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", help="a dask scheduler address (instead of a pool)")
    parser.add_argument("--every", type=int, default=44, help="cells between two samples")
    parser.add_argument("--n-noise", type=int, default=3)
    parser.add_argument("--cells-per-patch", type=int, default=20)
    parser.add_argument("--exposures", type=int, default=6)
    parser.add_argument("--size", type=int, default=3800, help="exposure side, px")
    args = parser.parse_args()
    start = time.perf_counter()
    rows: list[tuple[float, str, float]] = []

    def mark(what: str) -> None:
        rows.append((time.perf_counter() - start, what, rss_mb()))

    sampler = Sampler()
    from cellcoadd.builder import stream_patch
    from cellcoadd.geometry import SkyMap
    from cellcoadd.io.api import write_cells
    from cellcoadd.io.exposures.exposure_source import ExposureFile
    from cellcoadd.model.build_config import BuildConfig
    from cellcoadd.model.sources import describe

    work = Path(args.workdir)
    paths = write_inputs(work, args.cells_per_patch, args.exposures, args.size)
    patch = SkyMap.from_json((work / "skymap.json").read_text())[0].patch(1, 1)
    print(f"trace_build_memory: {machine_summary()}, load {os.getloadavg()[0]:.1f}")
    mark("imports done")
    inputs = [describe(ExposureFile(path)) for path in paths]
    where = {"scheduler": args.scheduler} if args.scheduler else {"workers": args.workers}
    config = BuildConfig(n_noise=args.n_noise)
    stream = stream_patch(patch, inputs, config, seed=0, progress=False, **where)
    mark("set-up done")

    def cells() -> Iterator[CellCoadd]:
        for number, cell in enumerate(stream, 1):
            yield cell
            del cell
            if number % args.every == 0:
                mark(f"{number} cells handed on")

    with stream:
        write_cells(stream.metadata, cells(), work / "trace.h5", overwrite=True)
    mark("written")
    sampler.stop()
    print(format_table(["s", "moment", "RSS MB"], rows, [".1f", "s", ".0f"]))
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak RSS: sampled {sampler.peak:.0f} MB, ru_maxrss {maxrss:.0f} MB; "
          f"load {os.getloadavg()[0]:.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
