"""The recommended default: the cheapest plain setting that is good on every bench scene.

"Good" is the ``TARGET_*`` criteria below; rows are those of the trade table
(``commands/trade.py``).
"""
import math
from collections.abc import Mapping, Sequence
from typing import Any

from .measure import Setting
from .tables import Row

#: (failed a criterion, CPU s per simulated s on the moving head, setting label, scene -> row)
Candidate = tuple[bool, float, str, dict[str, Row]]

# What "good enough" means for the recommendation (see ``recommend``).
TARGET_TIP_RMS_MM = 10.0      # on the moving-head reference ponytail (2.5 % of its length)
TARGET_ENERGY_DRIFT = 0.10    # |ΔE| / (E0 - E_rest) on the still-head scenes
TARGET_GAP_M = 1e-6


def recommend(rows: Sequence[Row], required: Sequence[str] = ('moving', 'release', 'shake', 'rope')
              ) -> tuple[Candidate | None, dict[str, Row] | None]:
    """The cheapest plain setting (banded, projection, exact head) good on all ``required`` scenes.

    Good: no guard reset and joint gap ≤ ``TARGET_GAP_M`` on every scene, tip RMS ≤
    ``TARGET_TIP_RMS_MM`` on the moving-head reference and on the violent shake (there only
    within its valid window, before the chaos takes over: surviving a shake without a reset is
    not enough, the constrained steps do that 20+ mm off), |energy drift| ≤
    ``TARGET_ENERGY_DRIFT`` on the still-head scenes (release, rope). Cost: CPU per simulated
    second on the moving head. The release's trajectory error is reported but not required
    (chaotic from the start: it says where the chaos takes over, not how good the solver is).
    """
    main = [r for r in rows if (r['scene'], r['n_segments']) in
            (('moving', 10), ('release', 10), ('shake', 10), ('rope', 40))]
    plain = [r for r in main if not r['tick_rate'] and r['projection']
             and not r['baumgarte_stiffness'] and not r['baumgarte_damping']]
    by_label: dict[str, dict[str, Row]] = {}
    for r in plain:
        by_label.setdefault(r['setting'], {})[r['scene']] = r
    all_by_label = by_label
    by_label = {k: {s: r for s, r in v.items() if s in required} for k, v in by_label.items()}
    candidates: list[Candidate] = []
    for label, per in by_label.items():
        if 'moving' not in per:
            continue
        ok = all(r['stable'] and r['max_gap_m'] <= TARGET_GAP_M for r in per.values())
        ok = ok and all(per[s]['tip_rms_mm'] <= TARGET_TIP_RMS_MM
                        for s in ('moving', 'shake') if s in per)
        for s in ('release', 'rope'):
            if s in per:
                ok = ok and per[s]['energy_drift_max'] <= TARGET_ENERGY_DRIFT
        candidates.append((not ok, per['moving']['cpu_s_per_sim_s'], label, per))
    candidates.sort(key=lambda c: (c[0], c[1]))
    good = [c for c in candidates if not c[0]]
    best = good[0] if good else None
    if best:
        best = best[:3] + (all_by_label[best[2]],)
    current = all_by_label.get(Setting().label)
    return best, current


def recommendation(rows: Sequence[Row]) -> dict[str, Any]:
    """The recommendation (a dict): strict (every scene), without the shake, and the current."""
    best, current = recommend(rows)
    gentle, _ = recommend(rows, required=('moving', 'release', 'rope'))
    rec = dict(criteria=dict(tip_rms_mm_moving_and_shake=TARGET_TIP_RMS_MM,
                             energy_drift_still=TARGET_ENERGY_DRIFT, max_gap_m=TARGET_GAP_M,
                             cost='CPU per simulated second on the moving head'),
               recommended=best[2] if best else None,
               recommended_rows=best[3] if best else None)
    if gentle and (not best or gentle[2] != best[2]):
        rec['recommended_without_shake'] = gentle[2]
        rec['recommended_without_shake_rows'] = gentle[3]
    if current:
        rec['current_default'] = Setting().label
        rec['current_rows'] = current
    return rec


def summary_line(label: str, per: Mapping[str, Row]) -> str:
    """One line: the setting's cost and error on the moving head, its error on the others."""
    mv = per.get('moving')
    parts = []
    if mv:
        parts.append(f'moving-head tip RMS {mv["tip_rms_mm"]:.3g} mm '
                     f'(max {mv["tip_max_mm"]:.3g} mm), '
                     f'{mv["cpu_s_per_sim_s"] * 1e3:.0f} ms CPU per simulated s '
                     f'({mv["cpu_us_per_step"]:.0f} µs/step)')
    for s in ('release', 'shake', 'rope'):
        if s in per:
            r = per[s]
            drift = r.get('energy_drift_max')
            e = ('' if drift is None or not math.isfinite(drift)
                 else f', |ΔE| {100 * drift:.2g}%')
            parts.append(f'{s}: RMS {r["tip_rms_mm"]:.3g} mm{e}'
                         + ('' if r['stable'] else f' ({r["resets"]} guard resets)'))
    return f'{label}: ' + '; '.join(parts)

