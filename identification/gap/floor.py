"""The noise floor a gap is judged against: whitening, repeat scatter and the floor's size."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from identification.gap.data import Groups, repeat_scatter_um

MIN_REPEAT_DOF = 6
REPEAT_INFLATE = 1.2  # repeats clearly worse than the trigger noise alone explains


def whiteners(groups: Groups) -> np.ndarray:
    """Per group (G, 4, 4): the inverse Cholesky factor of the centre covariance and the
    form residual's variance (the form row zero where there is no form residual)."""
    cov = np.zeros((len(groups), 4, 4))
    cov[:, :3, :3] = groups.centre_cov_um2
    cov[:, 3, 3] = groups.sigma_touch_um**2
    w = np.linalg.inv(np.linalg.cholesky(cov))
    if groups.channels < 4:  # no usable form residual: a zero row, not an observation
        w[:, 3, :] = 0.0
    return w


def repeat_floor(groups: Groups) -> tuple[Groups, str]:
    """With repeated ball-poses, the centre scatter between repeats is the better floor: it
    holds every non-repeatable error (indexing, clamping), the form residual only the trigger
    noise. Where it is clearly larger, the difference is added per axis to the centre
    covariances (an independent per-visit scatter on top of the sphere fit's)."""
    rep = repeat_scatter_um(groups)
    if rep is None:
        return groups, ""
    std, dof = rep
    sphere = np.sqrt(np.mean(np.diagonal(groups.centre_cov_um2, axis1=1, axis2=2), axis=0))
    xyz = "/".join(f"{v:.3f}" for v in std)
    if dof < MIN_REPEAT_DOF or np.all(std <= REPEAT_INFLATE * sphere):
        return groups, f"; repeats agree ({xyz} µm x/y/z, {dof} dof)"
    extra = np.diag(np.maximum(std ** 2 - sphere ** 2, 0.0))
    scaled = replace(groups, centre_cov_um2=groups.centre_cov_um2 + extra[None],
                     sigma_dof=min(groups.sigma_dof, dof))
    return scaled, (f"; per-visit scatter between repeats added to the centre covariances "
                    f"({xyz} µm x/y/z vs {'/'.join(f'{v:.3f}' for v in sphere)} µm from the "
                    f"form residuals, {dof} dof)")


def noise_floor_um(groups: Groups) -> float:
    """RMS noise floor per observation channel (µm): centre covariances plus the form
    residual's variance where there is one."""
    form_var = groups.sigma_touch_um**2 if groups.channels == 4 else 0.0
    return float(np.sqrt(np.mean(
        (np.trace(groups.centre_cov_um2, axis1=1, axis2=2) + form_var) / groups.channels)))
