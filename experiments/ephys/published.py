"""Published physiology to set beside the model's recordings, each value with the source text it was read in.

A dataset here holds only numbers read in a citable source text (paper, figure or table, page); a
number derived from them says how. :func:`looming_agreement` scores a looming recording against
:data:`LGMD_PEAK_TIME`; :func:`edges_agreement` scores an edges recording against
:data:`T4_T5_SELECTIVITY`, a qualitative finding (which polarity, that every layer is direction selective)
whose source states no number.

Each dataset is a dict: ``citation``, ``doi``, ``source`` (figure/table and where its text was
read), ``measured`` (what and in which animal), ``values`` (numbers with units in their keys),
``digitised`` (how the values were obtained: read in the text, read off a figure, or derived).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["LGMD_PEAK_TIME", "T4_T5_SELECTIVITY", "DATASETS", "lgmd_peak_time_s", "looming_agreement",
           "edges_agreement"]

#: The locust LGMD/DCMD's time of peak firing during a looming approach is linear in l/|v|: it peaks a fixed
#: delay δ after the object's angular size crosses a threshold θ_thres. Fig. 5's caption gives both.
LGMD_PEAK_TIME = {
    "citation": "Gabbiani F, Krapp HG, Laurent G (1999) Computation of object approach by a wide-field, "
                "motion-sensitive neuron. J Neurosci 19(3):1122-1141",
    "doi": "10.1523/JNEUROSCI.19-03-01122.1999",
    "source": "Fig. 5 and its caption (J Neurosci 19:1122-1141; PMC6782150, figure F5): the DCMD's peak firing "
              "follows Eq. 5 for l/|v| = 10, 30 and 50 ms; the peak comes delta = 27 ms after the approaching "
              "square subtends theta_thres = 24 degrees, the same for all three",
    "measured": "locust DCMD, the LGMD's postsynaptic target: time of peak firing rate "
                "relative to collision for a dark square approaching at constant speed, half-size l, speed v",
    "values": {"delta_s": 0.027, "theta_threshold_deg": 24.0, "l_over_v_s": [0.010, 0.030, 0.050]},
    "digitised": "delta and theta_thres read in the caption of Fig. 5 (numbers printed there, not read off "
                 "the plot); the line t_peak = -alpha * l/|v| + delta with alpha = 1/tan(theta_thres/2) = 4.70 "
                 "is derived from them with the stimulus' own geometry, theta(t) = 2 atan(l / (|v| * (-t)))",
}

#: T4 cells answer moving brightness increments (ON edges), T5 cells decrements (OFF edges); each of the four
#: subtypes of either is selective for one cardinal direction and projects to one lobula-plate layer.
T4_T5_SELECTIVITY = {
    "citation": "Haag J, Mishra A, Borst A (2017) A common directional tuning mechanism of Drosophila "
                "motion-sensing neurons in the ON and in the OFF pathway. eLife 6:e29044; the finding is Maisak MS "
                "et al. (2013) A directional tuning map of Drosophila elementary motion detectors. Nature "
                "500:212-216 (doi:10.1038/nature12320), which Haag et al. cite for it",
    "doi": "10.7554/eLife.29044",
    "source": "Haag et al. 2017, Introduction (eLife's JATS text, elife-29044-v2.xml): the four T4 subtypes respond "
              "selectively to brightness increments moving along one of the four cardinal directions, the four T5 "
              "subtypes selectively to brightness decrements along the same four; layers 1-4 of the lobula plate "
              "take front-to-back, back-to-front, upward and downward. Haag J, Arenz A, Serbe E, Gabbiani F, "
              "Borst A (2016) eLife 5:e17421 (doi:10.7554/eLife.17421), Results: layer-3 T4 cells recorded "
              "there confirm their preference for luminance increments",
    "measured": "Drosophila T4 and T5 cells (two-photon calcium imaging): the contrast polarity of moving edges each "
                "responds to, and each subtype's preferred cardinal direction",
    "values": {"t4_preferred_polarity": "on", "t5_preferred_polarity": "off",
               "layer_preferred_direction": {"1": "front_to_back", "2": "back_to_front", "3": "upward",
                                             "4": "downward"}},
    "digitised": "qualitative statements read in the text; the text states no direction-selectivity index and no "
                 "ON/OFF ratio, so none is stored (none was read off a figure either)",
}

DATASETS = {"lgmd_peak_time": LGMD_PEAK_TIME, "t4_t5_selectivity": T4_T5_SELECTIVITY}


def lgmd_peak_time_s(l_over_v_s) -> np.ndarray:
    """The LGMD's time of peak firing (s, relative to collision, negative before it) at ``l_over_v_s`` (s).

    Parameters
    ----------
    l_over_v_s : float or array_like
        Half-size over approach speed l/|v| (s).

    Returns
    -------
    numpy.ndarray
        ``-l/|v| / tan(θ_thres/2) + δ`` (s), same shape as ``l_over_v_s``, from :data:`LGMD_PEAK_TIME`.
    """
    v = LGMD_PEAK_TIME["values"]
    alpha = 1.0 / math.tan(math.radians(v["theta_threshold_deg"]) / 2.0)
    return -alpha * np.asarray(l_over_v_s, dtype=float) + v["delta_s"]


def looming_agreement(l_over_v_s, t_peak_s) -> dict:
    """How the model's looming peak times compare with the LGMD's (:data:`LGMD_PEAK_TIME`).

    Parameters
    ----------
    l_over_v_s : array_like, shape (n,)
        l/|v| values (s).
    t_peak_s : array_like, shape (n,)
        The model's time of peak (s, relative to collision) at each; NaN where none.

    Returns
    -------
    dict
        ``slope_ratio`` (the model's fitted slope d t_peak / d(l/|v|) over the LGMD's, 1 = the same
        angular threshold), ``model_slope``, ``published_slope`` (1), ``model_delta_s`` and
        ``published_delta_s`` (the fits' intercepts, s), ``model_theta_threshold_deg`` (the angular
        threshold the model's slope implies, 2·atan(1/|slope|), degree) and
        ``published_theta_threshold_deg``; NaN where fewer than two peak times are finite.
    """
    lv = np.asarray(l_over_v_s, dtype=float)
    tp = np.asarray(t_peak_s, dtype=float)
    ok = np.isfinite(tp) & np.isfinite(lv)
    pub = LGMD_PEAK_TIME["values"]
    pub_slope = -1.0 / math.tan(math.radians(pub["theta_threshold_deg"]) / 2.0)
    out = dict(published_slope=pub_slope, published_delta_s=pub["delta_s"],
               published_theta_threshold_deg=pub["theta_threshold_deg"], slope_ratio=float("nan"),
               model_slope=float("nan"), model_delta_s=float("nan"), model_theta_threshold_deg=float("nan"))
    if ok.sum() < 2 or np.ptp(lv[ok]) == 0:
        return out
    slope, delta = np.polyfit(lv[ok], tp[ok], 1)
    out.update(model_slope=float(slope), model_delta_s=float(delta), slope_ratio=float(slope / pub_slope),
               model_theta_threshold_deg=float(2.0 * math.degrees(math.atan(1.0 / abs(slope))))
               if slope != 0 else float("nan"))
    return out


def edges_agreement(ds) -> dict:
    """How an ``edges`` recording's T4/T5 layers compare with :data:`T4_T5_SELECTIVITY`.

    Parameters
    ----------
    ds : xarray.Dataset
        An edges recording: ``t4_mean_response`` and ``t5_mean_response`` (polarity × direction ×
        preferred_direction, each layer's mean response), ``t4_dsi`` and ``t5_dsi`` (preferred_direction).

    Returns
    -------
    dict
        Per cell ``c`` in t4, t5: ``{c}_published_polarity`` ("on" or "off"), ``{c}_polarity_index``
        ((R_published − R_other)/(R_published + R_other) with R a polarity's response of each layer to motion
        along its own preferred direction, averaged over the layers; +1: only the published polarity drives
        it, −1: only the other; NaN where both are 0) and ``{c}_selective_fraction`` (the fraction of layers
        whose DSI is > 0; the published finding: every layer, 1). ``polarity_agrees``: 1.0 when both polarity
        indices are > 0, else 0.0.
    """
    pub = T4_T5_SELECTIVITY["values"]
    out = {}
    for cell in ("t4", "t5"):
        m = ds[f"{cell}_mean_response"]
        want = pub[f"{cell}_preferred_polarity"]
        other = "off" if want == "on" else "on"
        r = {}
        for pol in (want, other):
            x = m.sel(polarity=pol)
            # each layer's response to motion along its own preferred direction
            r[pol] = float(np.mean([float(x.sel(direction=d, preferred_direction=d))
                                    for d in m.preferred_direction.values]))
        total = r[want] + r[other]
        dsi = np.asarray(ds[f"{cell}_dsi"].values, dtype=float)
        out[f"{cell}_published_polarity"] = want
        out[f"{cell}_polarity_index"] = float((r[want] - r[other]) / total) if total > 0 else float("nan")
        out[f"{cell}_selective_fraction"] = float(np.mean(dsi > 0)) if dsi.size else float("nan")
    out["polarity_agrees"] = float(out["t4_polarity_index"] > 0 and out["t5_polarity_index"] > 0)
    return out
