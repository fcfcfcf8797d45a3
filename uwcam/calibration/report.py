"""Plots and a self-contained HTML report of a calibration (matplotlib, PNGs embedded as base64).

The same figures serve ``uwcam calibrate --report`` and the daemon's calibration session
(``GET /api/v1/calibration/session/plots/{name}.png``).
"""

from __future__ import annotations

import base64
import html
import io

import numpy as np
from numpy.typing import NDArray

from uwcam.calibration.fit import CalibrationDetails
from uwcam.extras import require_extra
from uwcam.optics.calibration_variance import calibration_path_variance
from uwcam.optics.geometry import camera_range_derivative, path_length_from_camera_range
from uwcam.optics.noise import signal_variance

PLOTS = {
    "log-ratio": "ln(E_k/E_ref) against path length at each distance, with the fitted line per channel pair",
    "residuals": "residuals of the fit at each distance, with ±1σ from the noise model",
    "noise": "pixel noise variance against signal: measured points and the fitted noise model per channel",
    "overlay": "the nearest distance's image with the pixels used for the fit and the black patch outlined",
    "range-sigma": "predicted range σ against range, one pixel of a surface like the target on the optical axis, exposed like the calibration's brightest frame",
}


def _figure():
    matplotlib = require_extra("reports")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    _figure().close(fig)
    return buf.getvalue()


def predicted_range_sigma(details: CalibrationDetails, ranges_m: NDArray) -> tuple[NDArray, NDArray]:
    """(σ from pixel noise, σ with the calibration's covariance), metres, at camera ranges (m) on the
    optical axis for one frame of a surface like the target. The colour at each path length follows
    a line fitted to ln(mean E_k) over the calibration distances; the exposure puts the brightest
    channel at the brightest mean level seen during calibration."""
    profile = details.profile
    paths = np.array([g.path_length_m for g in details.groups])
    means = np.array([g.mean_frame[g.target].mean(axis=0) for g in details.groups])
    lamp = np.array(profile.lamp_position_m)
    d_t = path_length_from_camera_range(np.asarray(ranges_m, dtype=np.float64), lamp)
    slope, intercept = np.polyfit(paths, np.log(np.maximum(means, 1e-30)), 1)
    e = np.exp(intercept + np.outer(d_t, slope))  # (R, N)
    # Exposure set for each range as the camera would (auto-exposure, or a crew): the brightest
    # channel at the brightest level seen during calibration.
    e = e * (means.max() / e.max(axis=1, keepdims=True))
    var = signal_variance(e, profile.array("read_noise"), profile.array("shot_gain"), profile.quantisation_step,
                          profile.array("fixed_pattern"))
    var = np.maximum(var, 1e-12)
    usable = (e > profile.array("noise_floor")) & (e < profile.saturation_level)
    w = np.where(usable, e * e / var, 0.0)
    c = profile.array("attenuation_difference")
    with np.errstate(divide="ignore", invalid="ignore"):
        sw = w.sum(axis=1, keepdims=True)
        dc = c - (w * c).sum(axis=1, keepdims=True) / sw
        pixel = 1.0 / (w * dc * dc).sum(axis=1)
    cal = calibration_path_variance(w, c, d_t, *profile.covariance_blocks())
    deriv = camera_range_derivative(d_t, lamp)
    return np.sqrt(deriv**2 * pixel), np.sqrt(deriv**2 * (pixel + cal))


def figures(details: CalibrationDetails) -> dict[str, bytes]:
    """Every plot of :data:`PLOTS` as PNG bytes."""
    return {name: figure(details, name) for name in PLOTS}


def figure(details: CalibrationDetails, name: str) -> bytes:
    """One plot of :data:`PLOTS` as PNG bytes."""
    plt = _figure()
    profile = details.profile
    names = profile.channel_names
    ref = profile.reference_index
    paths = np.array([g.path_length_m for g in details.groups])
    logs = np.array([g.log_signal for g in details.groups])
    lv = np.array([g.log_variance for g in details.groups])
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    if name == "log-ratio":
        x = np.linspace(0, paths.max() * 1.1, 50)
        for k, ch in enumerate(names):
            if k == ref:
                continue
            y = logs[:, k] - logs[:, ref]
            line = ax.errorbar(paths, y, yerr=np.sqrt(lv[:, k] + lv[:, ref]), fmt="o", label=f"{ch}/{names[ref]}")
            v, b = profile.channels[k].attenuation_difference, profile.channels[k].log_constant
            ax.plot(x, b - v * x, color=line[0].get_color(), lw=1,
                    label=f"fit: V = {v:+.4f} ± {profile.channels[k].attenuation_difference_std:.4f} 1/m")
        ax.set_xlabel("path length d_T (m)")
        ax.set_ylabel(f"ln(E_k / E_{names[ref]})")
        ax.legend(fontsize=8)
    elif name == "residuals":
        res = details.fit.residuals
        for k, ch in enumerate(names):
            if k == ref:
                continue
            ax.errorbar(paths + 0.01 * k, res[:, k], yerr=np.sqrt(lv[:, k] + lv[:, ref]), fmt="o", label=ch)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("path length d_T (m)")
        ax.set_ylabel("residual of ln ratio")
        ax.legend(fontsize=8)
    elif name == "noise":
        nf = details.noise
        for k, ch in enumerate(names):
            pts = [p for _, p in details.noise_points]
            e = np.array([p.mean[k] for p in pts])
            s = np.array([p.spatial_variance[k] for p in pts])
            line = ax.loglog(e, s, "o", ms=4, label=f"{ch} spatial (frames' average)")[0]
            t = [(p.mean[k], p.temporal_variance[k]) for p in pts if p.temporal_variance is not None]
            if t:
                ax.loglog(*np.array(t).T, "x", color=line.get_color(), label=f"{ch} temporal")
            xs = np.geomspace(max(e.min() / 2, 1e-3), e.max() * 2, 60)
            total = signal_variance(xs, nf.read_noise[k], nf.shot_gain[k], profile.quantisation_step, nf.fixed_pattern[k])
            ax.loglog(xs, total, "-", color=line.get_color(), lw=1,
                      label=f"{ch}: read {nf.read_noise[k]:.3g} DN, shot {nf.shot_gain[k]:.3g} DN/e⁻, fixed {nf.fixed_pattern[k]:.2%}")
        ax.set_xlabel("signal E (DN)")
        ax.set_ylabel("variance (DN²)")
        ax.legend(fontsize=6)
    elif name == "overlay":
        g = min(details.groups, key=lambda g: g.distance_m)
        img = np.maximum(g.mean_frame[:, :, :3], 0)
        top = np.percentile(img, 99.5) or 1.0
        ax.imshow(np.clip(img / top, 0, 1) ** (1 / 2.2))
        if g.fit_pixels is not None:
            ax.contour(g.fit_pixels, levels=[0.5], colors="lime", linewidths=1)
        if g.black is not None:
            ax.contour(g.black, levels=[0.5], colors="magenta", linewidths=1)
        ax.set_title(f"{g.distance_m:g} m: fit pixels (green), black patch (magenta)", fontsize=9)
        ax.axis("off")
    elif name == "range-sigma":
        r = np.linspace(0.5, 20.0, 80)
        pixel, total = predicted_range_sigma(details, r)
        ax.semilogy(r, pixel * 100, label="pixel noise only")
        ax.semilogy(r, total * 100, label="with the calibration's uncertainty")
        ax.set_xlabel("camera range (m)")
        ax.set_ylabel("σ of range, one pixel (cm)")
        ax.legend(fontsize=8)
    else:
        plt.close(fig)
        raise KeyError(name)
    ax.grid(True, which="both", alpha=0.3) if name != "overlay" else None
    fig.tight_layout()
    return _png(fig)


def html_report(details: CalibrationDetails, title: str | None = None, advice: str | None = None) -> str:
    """One self-contained HTML page: summary tables and every plot embedded as a base64 PNG; ``advice``:
    what the water asks of the rig (:func:`uwcam.calibration.rig_advice.calibration_rig_advice`), shown first."""
    p = details.profile
    title = title or f"uwcam calibration {p.name}"
    esc = html.escape
    rows = "".join(
        f"<tr><td>{esc(c.name)}</td><td>{c.attenuation_difference:+.5f} ± {c.attenuation_difference_std:.5f}</td>"
        f"<td>{c.log_constant:+.4f} ± {c.log_constant_std:.4f}</td><td>{c.read_noise:.3g}</td><td>{c.shot_gain:.3g}</td>"
        f"<td>{c.fixed_pattern:.3%}</td><td>{c.noise_floor:.3g}</td></tr>" for c in p.channels)
    dist = "".join(
        f"<tr><td>{g.distance_m:g}</td><td>{len(g.images)}</td><td>{g.path_length_m:.4f}</td>"
        f"<td>{'' if g.backscatter is None else ', '.join(f'{v:.2f}' for v in g.backscatter.level)}</td></tr>"
        for g in details.groups)
    cov = ""
    if p.covariance is not None:
        m = np.array(p.covariance.matrix)
        sd = np.sqrt(np.maximum(np.diag(m), 1e-300))
        corr = m / np.outer(sd, sd)
        head = "".join(f"<th>{esc(n)}</th>" for n in p.covariance.parameters)
        body = "".join(f"<tr><th>{esc(n)}</th>" + "".join(f"<td>{v:+.2f}</td>" for v in row) + "</tr>"
                       for n, row in zip(p.covariance.parameters, corr))
        cov = f"<h2>Correlations of the calibration</h2><table><tr><th></th>{head}</tr>{body}</table>"
    plots = "".join(
        f"<h2>{esc(name)}</h2><p>{esc(text)}</p><img alt='{esc(name)}' src='data:image/png;base64,"
        f"{base64.b64encode(png).decode('ascii')}'>" for (name, text), png in zip(PLOTS.items(), figures(details).values()))
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:1em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:2px 6px;text-align:right}}img{{max-width:100%}}</style></head>
<body><h1>{esc(title)}</h1>
<p>Created {esc(p.provenance.created)}; method: {esc(p.provenance.method)}; reference channel {esc(p.reference_channel)};
rms residual {p.provenance.rms_residual:.2e}.</p>
{"" if advice is None else f"<h2>The rig for this water</h2><p class='advice'>{esc(advice)}</p>"}
<h2>Channels</h2><table><tr><th>channel</th><th>c − c_ref (1/m)</th><th>log constant</th><th>read (DN)</th>
<th>shot (DN/e⁻)</th><th>fixed pattern</th><th>floor (DN)</th></tr>{rows}</table>
<h2>Distances</h2><table><tr><th>distance (m)</th><th>frames</th><th>path length (m)</th><th>backscatter at patch (DN)</th></tr>{dist}</table>
{cov}{plots}</body></html>
"""
