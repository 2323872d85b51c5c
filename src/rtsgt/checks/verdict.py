"""One verdict for a run: is this ground truth usable, and the reasons that matter.

Reads the self-checks' JSON-ready results (``RunRecord.self_checks``, ``distance_check``, the
kept poses) and ranks their findings: ``not usable as is`` (2), ``usable, with caveats`` (1),
notes (0). The CLI prints :meth:`RunVerdict.line`; ``summary.json`` records
:meth:`RunVerdict.to_dict`. The levels: docs/self-checks.md#the-runs-verdict.
"""

from __future__ import annotations

from dataclasses import dataclass

from rtsgt.filtering.gates import SURVEY_DISTANCE_WARNING_SIGMA

__all__ = ["Finding", "RunVerdict", "record_verdict", "run_verdict"]

#: The verdict's words by its worst finding's severity.
LEVELS = {0: "usable", 1: "usable, with caveats", 2: "not usable as is"}

#: The line names at most this many reasons (the rest are in summary.json and the report).
SHOWN_REASONS = 2

#: A share of rejected poses above this is a caveat.
REJECTED_SHARE_CAVEAT = 0.5


@dataclass(frozen=True)
class Finding:
    """What one check found: ``severity`` (0 note, 1 caveat, 2 not usable), the ``check``'s
    name and a short ``text`` with its numbers."""

    severity: int
    check: str
    text: str

    def to_dict(self) -> dict:
        return {"severity": self.severity, "check": self.check, "text": self.text}


@dataclass(frozen=True)
class RunVerdict:
    """The run's verdict: ``findings`` sorted by severity, worst first."""

    findings: tuple[Finding, ...]

    @property
    def severity(self) -> int:
        return max((f.severity for f in self.findings), default=0)

    @property
    def level(self) -> str:
        return LEVELS[self.severity]

    @property
    def usable(self) -> bool:
        return self.severity < 2

    @property
    def reasons(self) -> tuple[Finding, ...]:
        """The findings of the worst severity above notes, worst first."""
        return tuple(f for f in self.findings if f.severity == self.severity > 0)

    def line(self, where: str = "") -> str:
        """``verdict: <level>: <one or two reasons> (+N more ...)``; ``where`` names where the
        rest is (e.g. the run directory's summary.json)."""
        shown = self.reasons[:SHOWN_REASONS]
        text = f"verdict: {self.level}"
        if shown:
            text += ": " + "; ".join(f.text for f in shown)
        more = len(self.findings) - len(shown)
        if more and where:
            text += f"; {more} more in {where}"
        elif where:
            text += f"; details in {where}"
        return text

    def to_dict(self) -> dict:
        return {"level": self.level, "usable": self.usable,
                "findings": [f.to_dict() for f in self.findings]}


def _interval(v: dict) -> str:
    lo, hi = v["interval_95"]
    return f"[{lo:.2f}, {hi:.2f}]"


def _ranges(values: list[float]) -> str:
    lo, hi = min(values), max(values)
    return f"{lo:.1f} s" if round(lo, 1) == round(hi, 1) else f"{lo:.1f}-{hi:.1f} s"


def _names(keys) -> str:
    keys = list(keys)
    return keys[0] if len(keys) == 1 else ", ".join(keys[:-1]) + " and " + keys[-1]


def _distances(check: dict, out: list[Finding]) -> None:
    overall = check.get("overall") or {}
    if overall.get("verdict") == "optimistic":
        out.append(Finding(2, "inter-prism distances",
                           f"covariance too small: inter-prism z^2 {overall['mean_z2']:.2f} "
                           f"above its 95 % interval {_interval(overall)} over "
                           f"{overall['poses']} poses"))
    elif overall.get("verdict") == "pessimistic":
        out.append(Finding(0, "inter-prism distances",
                           f"covariance larger than the errors: inter-prism z^2 "
                           f"{overall['mean_z2']:.2f} below {_interval(overall)}"))
    bad = {k: v for k, v in (check.get("regimes") or {}).items()
           if v and v.get("verdict") == "optimistic"}
    if bad:
        out.append(Finding(1, "inter-prism distances", "covariance too small while "
                           + _names([f"{k} (z^2 {v['mean_z2']:.2f} > {v['interval_95'][1]:.2f})"
                                     for k, v in bad.items()])))


def _block_cv(check: dict, out: list[Finding]) -> None:
    entries = [("whole run", check.get("overall")), *(check.get("regimes") or {}).items()]
    bad = [(k, v) for k, v in entries if v and v.get("verdict") == "optimistic"]
    if bad:
        out.append(Finding(1, "block cross-validation",
                           "covariance too small across measurement gaps of 1-3 s: "
                           + _names([f"{k} NEES/dof {v['nees_per_dof']:.2f}" for k, v in bad])))
    low = [k for k, v in entries if v and v.get("verdict") == "pessimistic"]
    if low:
        out.append(Finding(0, "block cross-validation",
                           "covariance larger than the errors across measurement gaps: "
                           + _names(low)))


def _static(check: dict, carried: dict, out: list[Finding]) -> None:
    prisms = check.get("prisms") or {}
    level, corr, taus, high = [], [], [], []
    for pid, e in prisms.items():
        for name in ("range", "horizontal", "vertical"):
            c = e.get(name) or {}
            if (c.get("level") or {}).get("verdict") == "optimistic":
                level.append(f"{pid} {name}")
            if (c.get("level") or {}).get("verdict") == "pessimistic":
                high.append(f"{pid} {name}")
            co = c.get("correlation") or {}
            applied = (((carried.get("prisms") or {}).get(pid) or {}).get(name) or {}).get(
                "applied")
            if co.get("verdict") == "optimistic" and not applied:
                corr.append(f"{pid} {name}")
                if co.get("correlation_time_s") is not None:
                    taus.append(float(co["correlation_time_s"]))
    if corr:
        over = f" over {_ranges(taus)}" if taus else ""
        out.append(Finding(1, "static stretches",
                           f"static noise correlated{over}, not carried ({len(corr)} of "
                           f"{3 * len(prisms)} components; correlated_noise = \"inflate\" "
                           "carries it)"))
    if level:
        out.append(Finding(1, "static stretches",
                           f"static noise larger than predicted ({len(level)} of "
                           f"{3 * len(prisms)} components)"))
    if high:
        out.append(Finding(0, "static stretches",
                           f"static noise smaller than predicted ({len(high)} of "
                           f"{3 * len(prisms)} components)"))


def _raw_block_cv(check: dict, out: list[Finding]) -> None:
    overall = check.get("overall") or {}
    if overall.get("verdict") == "optimistic":
        out.append(Finding(2, "raw block cross-validation",
                           f"covariance too small: the raw measurements held out in blocks "
                           f"have NEES/dof {overall['nees_per_dof']:.2f} above "
                           f"{_interval(overall)} ({overall['blocks']} blocks)"))
    elif overall.get("verdict") == "pessimistic":
        out.append(Finding(0, "raw block cross-validation",
                           f"covariance larger than the errors: raw measurements' NEES/dof "
                           f"{overall['nees_per_dof']:.2f} below {_interval(overall)}"))
    bad = {k: v for k, v in (check.get("stations") or {}).items()
           if v.get("verdict") == "optimistic"}
    if bad:
        out.append(Finding(1, "raw block cross-validation", "covariance too small for station "
                           + _names([f"{k} (NEES/dof {v['nees_per_dof']:.2f} > "
                                     f"{v['interval_95'][1]:.2f})" for k, v in bad.items()])))


def _static_relative(check: dict, out: list[Finding]) -> None:
    lags = check.get("lags") or {}
    bad = {k: v for k, v in lags.items() if v.get("verdict") == "optimistic"}
    if bad:
        out.append(Finding(1, "static relative poses",
                           "covariance too small for motion over "
                           + _names([f"{k} s (NEES/dof {v['nees_per_dof']:.2f} > "
                                     f"{v['interval_95'][1]:.2f})" for k, v in bad.items()])
                           + " on the static stretches"))
    low = [k for k, v in lags.items() if v.get("verdict") == "pessimistic"]
    if low:
        out.append(Finding(0, "static relative poses",
                           "covariance larger than the errors for motion over "
                           + _names([f"{k} s" for k in low]) + " on the static stretches"))


def _gcp(check: dict, out: list[Finding]) -> None:
    bad = {s: v for s, v in (check.get("stations") or {}).items()
           if v.get("verdict") == "optimistic"}
    if bad:
        added = check.get("added_shot_sigma_mm") or {}
        carried = (f"; {added.get('horizontal', 0):.2f} mm horizontal, "
                   f"{added.get('vertical', 0):.2f} mm vertical added to each shot"
                   if any(added.values()) else "")
        factors = ", ".join(f"{v['variance_factor']:.1f}" for v in bad.values())
        out.append(Finding(1, "GCP fit",
                           f"GCP shots of station{'s' if len(bad) > 1 else ''} "
                           f"{_names(list(bad))} disagree more than the instrument model "
                           f"predicts (variance factor {factors}{carried})"))


def _structure(check: dict, out: list[Finding]) -> None:
    ck, po = check.get("clock") or {}, check.get("prism_orientation") or {}
    if ck.get("verdict") == "optimistic":
        out.append(Finding(2, "clock offsets",
                           f"the stations' clock offsets vary over the run: chi2/dof "
                           f"{ck['chi2_per_dof']:.2f} above {ck['critical']:.2f}"))
    if po.get("verdict") == "optimistic":
        out.append(Finding(2, "prism orientation",
                           f"the inter-prism residuals follow the prisms' viewing angle: F "
                           f"{po['f']:.2f} above {po['critical']:.2f}"))


def _survey(distance_check: dict, threshold: float, out: list[Finding]) -> None:
    bad = {k: v for k, v in (distance_check or {}).items()
           if v.get("ratio") is not None and abs(v["ratio"]) > threshold}
    if bad:
        out.append(Finding(2, "surveyed distances",
                           "tracked inter-prism distance "
                           + _names([f"{k} {v['median_deviation_mm']:+.1f} mm "
                                     f"({v['ratio']:+.1f} sigma)" for k, v in bad.items()])
                           + " off the survey: a prism moved or was mis-surveyed"))


def _dynamic(check: dict, out: list[Finding]) -> None:
    if check.get("verdict") == "optimistic":
        out.append(Finding(1, "dynamic calibration",
                           f"the inter-prism distances disagree with the calibration's model "
                           f"(variance factor {check['variance_factor']:.2f})"))
    bad = [s for s, v in (check.get("gcp_agreement") or {}).items()
           if v.get("verdict") == "disagree"]
    if bad:
        out.append(Finding(1, "dynamic calibration",
                           f"dynamic and GCP calibrations disagree for station"
                           f"{'s' if len(bad) > 1 else ''} {_names(bad)}"))


def _moved_prisms(joint: dict, out: list[Finding]) -> None:
    moved = {k: v for k, v in (joint.get("prisms") or {}).items() if v.get("moved")}
    for name, v in moved.items():
        shift = sum(x * x for x in v.get("shift_mm") or ()) ** 0.5
        largest = v.get("largest_sigma_mm")  # absent from runs written before it was
        sigma = "" if largest is None else f" (sigma up to {largest:.1f} mm)"
        out.append(Finding(1, "moved prism",
                           f"prism {name} moved {shift:.1f} mm from its survey: where the other "
                           f"prisms cannot place it only the motion model does{sigma}; a survey "
                           f"after the deployment would determine it"))
    carried = {k: v["moved_weight"] for k, v in (joint.get("prisms") or {}).items()
               if 0.0 < (v.get("moved_weight") or 0.0) < 1.0}
    if carried:  # docs/joint.md#which-prism-moved
        out.append(Finding(1, "which prism moved",
                           f"which prism moved is not decided: prisms {_names(sorted(carried))} "
                           f"each carried at weight {min(carried.values()):.2f} in the poses' "
                           f"covariance, which is larger for it; a survey after the deployment "
                           f"would decide"))


def _blind_moves(joint: dict, out: list[Finding]) -> None:
    """A note where a prism's move can be seen by no station (``blind_directions`` of
    ``summary.json``'s ``joint.prisms``): which prisms, along what (for three prisms the
    normal of their plane, the same for each), the poses' turn per mm of it and whether the
    poses carry such a move (``prism_stability_mm``; docs/joint.md#what-no-station-sees)."""
    blind = {k: v for k, v in (joint.get("prisms") or {}).items()
             if v.get("blind_directions")}  # absent from runs written before it was
    if not blind:
        return
    turns = [t for v in blind.values() for t in v.get("blind_turn_mrad_per_mm") or ()]
    dirs = [d for v in blind.values() for d in v["blind_directions"]]
    one = all(max(abs(a - b) for a, b in zip(d, dirs[0], strict=True)) < 1e-6 for d in dirs)
    along = ("across their plane, along ("
             + ", ".join(f"{x:.2f}" for x in dirs[0]) + ") in the body frame," if one
             else "in the directions summary.json gives")
    size = (f"{min(turns):.2g} mrad" if max(turns) - min(turns) < 0.005 * max(turns)
            else f"{min(turns):.2g}-{max(turns):.2g} mrad")
    stability = joint.get("prism_stability_mm") or 0.0  # absent from older runs
    carried = (f"the poses carry a move of {stability:.3g} mm (1 sigma) there, as "
               f"[reference] prism_stability_mm says" if stability > 0 else
               "the poses take the survey there ([reference] prism_stability_mm would have "
               "them carry a move)")
    out.append(Finding(0, "what no station sees",
                       f"a move of prism{'s' if len(blind) > 1 else ''} {_names(list(blind))} "
                       f"{along} changes no inter-prism distance and is seen by no station: "
                       f"each mm of it turns every pose by {size}, and {carried}; a prism off "
                       f"their plane, a survey after the deployment or an IMU's gravity would "
                       f"see it"))


def run_verdict(self_checks: dict, *, kept: int, queried: int,
                distance_check: dict | None = None, correlated_noise: dict | None = None,
                survey_sigma: float = SURVEY_DISTANCE_WARNING_SIGMA,
                joint: dict | None = None) -> RunVerdict:
    """The verdict of a run from its ``self_checks`` (``RunRecord.self_checks``), the poses ``kept``
    of ``queried``, its ``distance_check`` (tracked distances against the survey; a pair over
    ``survey_sigma`` predicted sigmas is a finding), ``correlated_noise`` (what the GPs
    carried) and ``joint`` (``summary.json``'s ``joint``: a prism the joint engine found
    moved is a caveat, a move no station could see a note)."""
    out: list[Finding] = []
    if kept == 0:
        out.append(Finding(2, "poses", f"no pose passed the quality gates (0 of {queried})"))
    elif queried and (queried - kept) / queried > REJECTED_SHARE_CAVEAT:
        out.append(Finding(1, "poses", f"only {kept} of {queried} queried poses kept"))
    _distances(self_checks.get("inter_prism_distances") or {}, out)
    _structure(self_checks.get("inter_prism_structure") or {}, out)
    _survey(distance_check or {}, survey_sigma, out)
    _block_cv(self_checks.get("block_cv") or {}, out)
    _raw_block_cv(self_checks.get("raw_block_cv") or {}, out)
    _static(self_checks.get("static_noise") or {}, correlated_noise or {}, out)
    _static_relative(self_checks.get("static_relative") or {}, out)
    _gcp(self_checks.get("gcp_fit") or {}, out)
    _dynamic(self_checks.get("dynamic_calibration") or {}, out)
    _moved_prisms(joint or {}, out)
    _blind_moves(joint or {}, out)
    return RunVerdict(tuple(sorted(out, key=lambda f: -f.severity)))


def record_verdict(record) -> RunVerdict:
    """:func:`run_verdict` of a run record (:class:`rtsgt.record.RunRecord`, or a
    :class:`~rtsgt.record.PositionRunRecord`, whose positions are all kept)."""
    gt = getattr(record, "groundtruth", None)
    queried = int(record.prisms_t.shape[0])
    return run_verdict(record.self_checks, kept=queried if gt is None else len(gt),
                       queried=queried,
                       distance_check=getattr(record, "distance_check", None),
                       correlated_noise=record.correlated_noise,
                       joint=getattr(record, "joint", None))
