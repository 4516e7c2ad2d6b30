"""The background field from the International Geomagnetic Reference Field (IGRF).

A thin wrapper around the maintained ``ppigrf`` package that returns the main field in the
project's frame and unit: ENU (east, north, up), nT. ``ppigrf.igrf`` already returns the
geodetic components ``Be, Bn, Bu`` in nT, so no sign change is needed.
"""

from __future__ import annotations

import datetime as _dt
import warnings

import numpy as np
from numpy.typing import NDArray

from pipeline.core.errors import ConfigError

# The IGRF-14 coefficients shipped with ppigrf cover 1900..2030; outside that the model is an
# extrapolation nobody should survey with.
_FIRST_YEAR = 1900
_LAST_YEAR = 2030


def _as_datetime(date: _dt.datetime | _dt.date | str) -> _dt.datetime:
    """Return a naive UTC datetime from a datetime, a date or an ISO 8601 string."""
    if isinstance(date, str):
        try:
            d = _dt.datetime.fromisoformat(date.strip().replace("Z", "+00:00"))
        except ValueError as exc:
            raise ConfigError(f"date {date!r} is not an ISO 8601 date") from exc
    elif isinstance(date, _dt.datetime):
        d = date
    elif isinstance(date, _dt.date):
        d = _dt.datetime(date.year, date.month, date.day)
    else:
        raise ConfigError(f"date must be a date, datetime or ISO string, got {date!r}")
    if d.tzinfo is not None:
        d = d.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    return d


def igrf_enu_nT(
    lat_deg: float, lon_deg: float, alt_m: float, date: _dt.datetime | _dt.date | str
) -> NDArray[np.float64]:
    """IGRF main field at a place and date, ENU, nT.

    Parameters
    ----------
    lat_deg, lon_deg : float
        Geodetic latitude and longitude, degrees (north and east positive).
    alt_m : float
        Height above the WGS-84 ellipsoid, metres.
    date : datetime, date or str
        When; an ISO 8601 string such as ``"2026-01-01"`` is accepted.

    Returns
    -------
    ndarray, shape (3,)
        ``[B_east, B_north, B_up]`` in nT.

    Raises
    ------
    ConfigError
        On a place or date outside the model's domain.

    """
    import ppigrf

    d = _as_datetime(date)
    if not -90.0 <= float(lat_deg) <= 90.0:
        raise ConfigError(f"latitude {lat_deg} deg is outside [-90, 90]")
    if not _FIRST_YEAR <= d.year < _LAST_YEAR:
        raise ConfigError(
            f"date {d.date()} is outside the IGRF-14 span {_FIRST_YEAR}..{_LAST_YEAR}"
        )
    with warnings.catch_warnings():
        # ppigrf emits pandas/numpy deprecation noise on some versions; the values are fine.
        warnings.simplefilter("ignore")
        be, bn, bu = ppigrf.igrf(float(lon_deg), float(lat_deg), float(alt_m) * 1e-3, d)
    return np.array([np.ravel(be)[0], np.ravel(bn)[0], np.ravel(bu)[0]], dtype=np.float64)
