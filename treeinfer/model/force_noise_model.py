"""The force-noise term of a run (:class:`ForceNoiseModel`: enough to rebuild ``C`` for any pull,
at one reference or one per lobe, :mod:`treeinfer.model.force_noise_local`) and the training
pulls' basis with the bias correction's slope (:func:`training_basis`). Apart from
:mod:`treeinfer.model.force_noise`, which the modules used here import."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .force_noise import BIAS_STEP, force_noise_basis
from .force_noise_bias import with_bias_slope
from .force_noise_local import split, stack

__all__ = ["ForceNoiseModel", "training_basis"]


class ForceNoiseModel(NamedTuple):
    """The force-noise term of a run: enough to rebuild ``C`` for any pull.

    sigma_force: N per sample. theta_ref: ``[2R]`` reference (log gains) of the linearisation,
    or ``[K, 2R]``: one per lobe of the posterior (:mod:`treeinfer.model.force_noise_local`).
    description: one line for logs. grasp_fraction: as in the run (None: the tree's).
    """

    sigma_force: float
    theta_ref: np.ndarray
    description: str
    grasp_fraction: object = None

    @property
    def references(self) -> np.ndarray:
        """``[K, 2R]`` the references as rows (K = 1 for a single ``[2R]`` reference)."""
        return np.asarray(self.theta_ref, float).reshape(-1, np.shape(self.theta_ref)[-1])

    def basis(self, sim, forces, mask=None):
        """Basis of the force-induced covariance for the pulls ``forces [B, T]`` (N); stacked
        (:mod:`treeinfer.model.force_noise_local`) when there are several references."""
        refs = self.references
        return stack(
            force_noise_basis(sim, r, forces, self.sigma_force, mask, self.grasp_fraction)._replace(
                theta_ref=r if len(refs) > 1 else None
            )
            for r in refs
        )

    def settings(self) -> dict:
        """JSON-ready record (``noise_force`` N, ``noise_force_reference`` log gains)."""
        return {
            "noise_force": self.sigma_force,
            "noise_force_reference": np.asarray(self.theta_ref, float).tolist(),
            "noise_force_rule": self.description,
            # the likelihood adds the corrected score's term (module docstring)
            "noise_force_bias_correction": f"corrected score, first order in the log gains "
            f"(slope by forward differences, step {BIAS_STEP:g})",
        }


def training_basis(sim, fmodel, obs):
    """The training pulls' force-noise basis with the bias correction's slope (the corrected
    score: the recorded force's noise biases the fit; force_noise docstring), at each of
    ``fmodel``'s references (stacked where there are several: force_noise_local)."""
    force, mask = np.asarray(obs.force), np.asarray(obs.mask, bool)
    refs = fmodel.references
    parts = split(fmodel.basis(sim, force, mask))
    return stack(
        with_bias_slope(sim, b, r, force, fmodel.sigma_force, mask, fmodel.grasp_fraction)
        for b, r in zip(parts, refs)
    )
