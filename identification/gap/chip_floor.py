"""What chip a run could not have seen: the outlier test's sensitivity by touch.

A chip of δ on an equator touch moves the fitted radius by δ/4 and the form residual by δ/2
(``identification.outliers``): the sphere stage names it at D = √((δ/4s_r)² + (δ/2s_f)²) ≥
``SPHERE_Z``. On the pole it moves neither — only the centre, by δ along the pole normal — so
the centre stage names it at δ / s_c ≥ ``CENTRE_Z``, with s_c the run's robust centre scale,
which holds every per-visit scatter (indexing, clamping) and the twin's misfit: the pole is
blind to chips the equator sees. Both also need ``MIN_SIZE_UM``. The sizes are the run's own
(its robust scales), stated in the report so that a missed pole chip is not a surprise.
"""

from __future__ import annotations

import math

from identification.outliers import CENTRE_Z, MIN_SIZE_UM, SPHERE_Z


def min_chip_um(radius_scale_um: float | None, form_scale_um: float | None,
                centre_scale_um: float | None) -> dict[str, float | None]:
    """{equator, pole}: the smallest single-touch chip (µm) this run's outlier test names
    (None where its stage did not run)."""
    equator = pole = None
    if radius_scale_um and form_scale_um:
        equator = SPHERE_Z / math.hypot(1 / (4 * radius_scale_um), 1 / (2 * form_scale_um))
        equator = max(equator, MIN_SIZE_UM)
    if centre_scale_um:
        pole = max(CENTRE_Z * centre_scale_um, MIN_SIZE_UM)
    return {"equator": None if equator is None else round(equator, 2),
            "pole": None if pole is None else round(pole, 2)}


def message(sizes: dict[str, float | None]) -> str:
    """'a chip smaller than 9.1 µm on the pole (3.2 µm on the equator) …' or ''."""
    if sizes["pole"] is None or sizes["equator"] is None:
        return ""
    return (f"a chip smaller than {sizes['pole']:.1f} µm on the pole ({sizes['equator']:.1f} µm "
            "on an equator touch) could not have been seen on this run: the pole only moves "
            "the centre, which the per-visit scatter blurs")
