r"""Rao-Blackwellised (marginalised) particle filter (``rbpf``): particles for the orientation (and the
curvature), a Kalman filter per particle for the position.

Where it applies: a model whose vector field does not depend on its positions (it declares them
``translation_states``: ``unicycle``, ``modified_unicycle``, ``mnm``, ``binm``), with every measurement
channel either a linear function of the positions alone (a position sensor: ``h`` selects translation
states; Gaussian likelihood) or a function of the other states alone (roll encoder, elastography,
tangent, field direction; any likelihood). Given a particle's orientation trajectory and the inputs, the
position is then linear-Gaussian, ``p_{k+1} = p_k + d_k(theta) + w_p``, ``y = H p + v``, and its
posterior is exact: a Gaussian whose covariance is the same for every particle of a run. Elsewhere
(``so3``, which has no position; a one-sided image plane, which bounds position and tangent together; a
Student-t position channel, which is not conjugate) :meth:`~RaoBlackwellisedParticleFilter.check` refuses
it and says why: use ``pf``.

The numerics are the bootstrap filter's with ``marginal`` set (:mod:`needlecli.observers.pf`): the same
prediction (the Kalman mean rides in the particle and the model moves it by the particle's own
displacement; process noise only on the particle states, ``Q_p`` added to the shared covariance), the
marginal likelihood ``N(y; H p_i, H P_p H^T + R)`` of a position sample, the Kalman update of ``p_i`` and
``P_p``, and the mixture's mean and covariance as the estimate.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from needlecli.models import StateSelection
from needlecli.observers.base import OBSERVERS
from needlecli.observers.pf import ParticleFilter, PFSettings
from needlecli.observers.ukf import check_filter


class RBPFSettings(PFSettings):
    type: Literal["rbpf"]  # type: ignore[assignment]


def channel_role(h, model) -> str | None:
    """How a channel's ``h`` (for ``model``'s state) stands to the positions: ``"linear"`` (it selects
    translation states only), ``"orientation"`` (it does not depend on them: checked at a generic state
    and one moved along every translation state), or None (both: not conditionally linear)."""
    trans = [model.index(k) for k in model.translation_states]
    if isinstance(h, StateSelection):
        idx = set(np.asarray(h.index).tolist())
        if idx <= set(trans):
            return "linear"
        if not idx & set(trans):
            return "orientation"
        return None
    params = {k: np.asarray(v, dtype=float) for k, v in model.param_arrays().items()}
    try:
        x0 = np.asarray(model.initial_state(params), dtype=float).reshape(-1)
    except Exception:  # noqa: BLE001 (a model without a default pose)
        return None
    x0 = x0 + 0.05 * (1 + np.arange(model.n)) / model.n
    x1 = x0.copy()
    x1[trans] += 10.0 * (1 + np.arange(len(trans)))
    with np.errstate(all="ignore"):
        try:
            same = np.allclose(np.asarray(h(x0[None]), dtype=float), np.asarray(h(x1[None]), dtype=float),
                               rtol=1e-12, atol=1e-12)
        except Exception:  # noqa: BLE001 (h that cannot be evaluated there)
            return None
    return "orientation" if same else None


@OBSERVERS.register("rbpf")
class RaoBlackwellisedParticleFilter(ParticleFilter):
    r"""Batched Rao-Blackwellised particle filter (module docstring): particles for the states the model's
    vector field depends on, a Kalman filter per particle for the positions.

    .. math:: p(x_{1:k} \mid y) = p(p_k \mid \theta_{1:k}, y)\, p(\theta_{1:k} \mid y),\qquad
        w_i \propto w_i\, \mathcal N(y; H p_i, H P_p H^T + R)
    """

    Settings = RBPFSettings
    marginal = True

    @classmethod
    def check(cls, settings, model, sensors):
        out, own = check_filter(settings, model, sensors, channel=cls._check_likelihood)
        if out or own is None:
            return out
        from needlecli.sensors.base import measurement_function

        mcls = type(own)
        if not mcls.translation_states:
            return [(("model",), f"model {mcls.registered_name!r} has no positions that its motion does not depend "
                               "on (translation_states): nothing to marginalise; use pf")]
        names = list(settings.measurements) or list(sensors)
        for name in names:
            sensor = sensors[name]
            loc = ("measurements", name) if settings.measurements else ("measurements",)
            if getattr(sensor, "inequality", False):
                if settings.measurements:
                    out.append((loc, f"sensor {name!r} bounds position and tangent together from one side: not "
                                     "conditionally linear; use pf"))
                continue
            h = measurement_function(sensor, own)
            if h is None:
                continue  # (default channels: those the model can predict)
            role = channel_role(h, own)
            if role is None:
                out.append((loc, f"sensor {name!r} measures the position and the other states together: not "
                                 "conditionally linear; use pf"))
            elif role == "linear" and name in settings.measurements and \
                    settings.measurements[name].likelihood != "gaussian":
                out.append(((*loc, "likelihood"), f"sensor {name!r} measures the position, which the Kalman filters "
                                                  "carry: a Gaussian likelihood only; use pf for a Student-t one"))
        return out
