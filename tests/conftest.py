"""Fixtures and test data shared by several test modules."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

#: A real DECam CCD (exposure 154912, CCD 12) from GalSim's test data, kept in the
#: repository (``tests/data/des``, BSD-3-Clause) so that tests reading it never skip.
DES_DATA = Path(__file__).resolve().parent / "data" / "des"
#: Its primary header with the real TPV WCS (no pixels; the CCD is 2048 x 4096).
DES_HEADER = DES_DATA / "DECam_00154912_12_header.fits"
#: The PSFEx model fitted on that CCD.
DES_PSF = DES_DATA / "DECam_00154912_12_psfcat.psf"


@pytest.fixture(scope="module")
def dask_client() -> Iterator[Any]:
    """A ``distributed.Client`` on a LocalCluster of 2 single-threaded worker processes
    (skips when dask.distributed is not installed)."""
    distributed = pytest.importorskip("distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        yield client
