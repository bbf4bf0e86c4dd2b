"""Cost of sending a WCS to another process: astropy's pickle against ``ExactWCS``'s.

For a tract WCS (TAN), a TAN-SIP WCS and a TPV WCS (PV distortion terms), times ``--n``
pickle round trips (``pickle.loads(pickle.dumps(wcs))``) of the plain astropy WCS (a FITS
file of 14-digit cards: what ``canonical_wcs`` did before) and of the same WCS as an
``ExactWCS`` (wcslib's 17-digit header plus the exact parameters), and prints both per
round trip with the pickled size. Also checks that the ExactWCS comes back bit for bit.

Run as ``.venv/bin/python benchmarks/bench_wcs_pickle.py [--n N]``.
"""

from __future__ import annotations

import argparse
import os
import pickle
import time

import numpy as np
from astropy.wcs import WCS, Sip

from cellcoadd.geometry import SkyMap
from cellcoadd.geometry.exact_wcs import apply_wcs_exact_parameters, wcs_exact_parameters
from cellcoadd.geometry.wcs_utils import canonical_wcs


def _tpv_wcs() -> WCS:
    """A TPV WCS shaped like a DECam CCD's (CRPIX far off the chip, PV terms)."""
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TPV", "DEC--TPV"]
    wcs.wcs.crval = [104.75671214061234, -55.946675123456789]
    wcs.wcs.crpix = [8914.4, -6470.667]
    wcs.wcs.cd = [[1.9035401187e-08, 7.2874920845e-05], [-7.2855364817e-05, 1.9035401187e-08]]
    pv = [(i, m, (-1) ** m * 10.0 ** -(m % 5 + 2) / 3.0) for i in (1, 2) for m in range(11)]
    wcs.wcs.set_pv([(i, m, 1.0 if m == 1 else v) for i, m, v in pv])
    wcs.wcs.set()
    return wcs


def _sip_wcs() -> WCS:
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
    wcs.wcs.crval = [53.163590156789012, -27.782300987654321]
    wcs.wcs.crpix = [2036.5123456789012, 1999.8765432109877]
    wcs.wcs.cd = [[-5.5478120591e-05 / 3.0, 1.2e-07 / 7.0], [1.1e-07 / 3.0, 5.5541e-05 / 7.0]]
    a = np.zeros((4, 4))
    b = np.zeros((4, 4))
    a[2, 0], a[1, 1], a[3, 0] = 1.2345678901234567e-6, -1e-6 / 3.0, 1e-10 / 7.0
    b[0, 2], b[1, 1], b[0, 3] = 7.1428571428571428e-7, 1e-6 / 3.0, -1e-10 / 7.0
    wcs.sip = Sip(a, b, None, None, wcs.wcs.crpix)
    wcs.wcs.set()
    return wcs


def _per_round_trip(wcs: WCS, n: int) -> float:
    start = time.perf_counter()
    for _ in range(n):
        pickle.loads(pickle.dumps(wcs))
    return (time.perf_counter() - start) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=10_000, help="round trips per WCS and form")
    args = parser.parse_args()
    tract = SkyMap.named("lsst_cells_v1")[9469].wcs
    plain_tract = WCS(tract.to_header(relax=True))  # a plain astropy WCS, same parameters
    apply_wcs_exact_parameters(plain_tract, wcs_exact_parameters(tract))
    print(f"{args.n} pickle round trips per WCS; load average {os.getloadavg()[0]:.1f}")
    print(f"{'WCS':8} {'astropy':>10} {'ExactWCS':>10} {'ratio':>6} {'bytes':>12}")
    for name, plain in (("TAN", plain_tract), ("TAN-SIP", _sip_wcs()), ("TPV", _tpv_wcs())):
        exact = canonical_wcs(plain)
        received = pickle.loads(pickle.dumps(exact))
        assert (
            wcs_exact_parameters(received)
            == wcs_exact_parameters(exact)
            == (wcs_exact_parameters(plain))
        ), name
        old, new = _per_round_trip(plain, args.n), _per_round_trip(exact, args.n)
        sizes = f"{len(pickle.dumps(plain))}/{len(pickle.dumps(exact))}"
        print(f"{name:8} {old * 1e3:8.3f}ms {new * 1e3:8.3f}ms {old / new:6.1f} {sizes:>12}")
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
