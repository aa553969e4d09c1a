"""Figures of the benchmark (matplotlib, Agg backend; PNG files)."""
import math

import numpy as np

__all__ = ['pareto_plot', 'scaling_plot', 'mujoco_plot', 'energy_plot', 'pareto_front']


def _plt():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def pareto_front(points):
    """Indices of the non-dominated points of ``[(cost, error), ...]`` (both minimised)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best * (1.0 - 1e-6):
            front.append(i)
            best = points[i][1]
    return front


def _style(row):
    color = {'rk4': 'tab:blue', 'rattle': 'tab:green'}.get(row.get('integrator'), 'tab:orange')
    marker = 'o'
    if row.get('tick_rate'):
        marker = '^'
    elif row.get('baumgarte_stiffness') or row.get('baumgarte_damping'):
        marker = 'D'
    elif row.get('projection') is False:
        marker = 'x'
    return color, marker


def pareto_plot(rows, path, scenes, mujoco_rows=(), recommended=None, title=None):
    """Cost per simulated second vs tip RMS error, one panel per scene, log-log, labelled.

    Unstable settings (the guard reset the chain) are drawn as red crosses at the top edge.
    The Pareto front of the stable settings is the dashed line; ``recommended`` (a setting
    label) is ringed.
    """
    plt = _plt()
    n = len(scenes)
    cols = 2 if n > 1 else 1
    nrows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(7.5 * cols, 5.6 * nrows), squeeze=False)
    for ax, scene in zip(axes.ravel(), scenes, strict=False):   # (a spare panel: empty)
        _pareto_panel(plt, ax, rows, scene, mujoco_rows, recommended)
    for ax in axes.ravel()[n:]:
        ax.axis('off')
    fig.suptitle(title or 'Speed/accuracy trade: one point per setting')
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _pareto_panel(plt, ax, rows, scene, mujoco_rows, recommended):
    """One scene's panel of ``pareto_plot``: our settings, the front, MuJoCo's points, legend."""
    rs = [r for r in rows if r['scene'] == scene[0] and r['n_segments'] == scene[1]]
    stable = [r for r in rs if r['stable'] and r['tip_rms_mm'] > 0]
    top = max([r['tip_rms_mm'] for r in stable] + [1.0]) * 3.0
    for r in rs:
        _setting_point(ax, r, top, recommended)
    if stable:
        pts = [(r['cpu_s_per_sim_s'], r['tip_rms_mm']) for r in stable]
        front = [pts[i] for i in pareto_front(pts)]
        ax.plot([p[0] for p in front], [p[1] for p in front], 'k--', lw=0.8, zorder=2,
                label='Pareto front (ours)')
    unstable = [r['setting'] for r in rs if not r['stable']]
    if unstable:
        ax.text(0.99, 0.99, 'guard reset (red x, drawn at the top):\n' + '\n'.join(unstable),
                transform=ax.transAxes, ha='right', va='top', fontsize=6, color='red',
                bbox=dict(facecolor='white', alpha=0.8, edgecolor='none'))
    mj = [r for r in mujoco_rows if r['scene'] == scene[0] and r['n_segments'] == scene[1]
          and r['engine'] == 'mujoco']
    for r in mj:
        x = r['cpu_s_per_sim_s']
        y = r['tip_rms_mm'] if r['stable'] else top
        ax.scatter([x], [y], c='tab:purple' if r['stable'] else 'red', marker='P', s=50,
                   zorder=3)
        ax.annotate(f'MuJoCo {r["dt_label"]}' + ('' if r['stable'] else ' (unstable)'), (x, y),
                    textcoords='offset points', xytext=(4, -9), fontsize=6.5,
                    color='tab:purple')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('CPU seconds per simulated second')
    ax.set_ylabel('tip RMS error vs converged reference (mm)')
    ax.set_title(f'{scene[0]} (N = {scene[1]})')
    ax.grid(True, which='both', lw=0.3, alpha=0.5)
    handles = [
        plt.Line2D([], [], color='tab:blue', marker='o', ls='', label='RK4'),
        plt.Line2D([], [], color='tab:orange', marker='o', ls='', label='symplectic Euler'),
        plt.Line2D([], [], color='tab:green', marker='o', ls='', label='RATTLE'),
        plt.Line2D([], [], color='gray', marker='x', ls='', label='no projection'),
        plt.Line2D([], [], color='gray', marker='D', ls='', label='Baumgarte, no projection'),
        plt.Line2D([], [], color='gray', marker='^', ls='', label='head at frames (tick)'),
        plt.Line2D([], [], color='red', marker='x', ls='', label='unstable (guard reset)'),
        plt.Line2D([], [], color='k', ls='--', label='Pareto front'),
    ]
    if mj:
        handles.append(plt.Line2D([], [], color='tab:purple', marker='P', ls='',
                                  label='MuJoCo RK4'))
    ax.legend(handles=handles, fontsize=6.5, loc='lower left')


def _setting_point(ax, r, top, recommended):
    """One setting's point: coloured by integrator if stable, a red cross at ``top`` if not."""
    x = r['cpu_s_per_sim_s']
    if r['stable']:
        color, marker = _style(r)
        ax.scatter([x], [max(r['tip_rms_mm'], 1e-6)], c=color, marker=marker, s=36,
                   zorder=3)
        y = max(r['tip_rms_mm'], 1e-6)
    else:
        ax.scatter([x], [top], c='red', marker='x', s=40, zorder=3)
        y = top
    if r['stable']:
        ax.annotate(r['setting'], (x, y), textcoords='offset points', xytext=(4, 3),
                    fontsize=6.5)
    if recommended and r['setting'] == recommended:
        ax.scatter([x], [y], s=160, facecolors='none', edgecolors='k', linewidths=1.5,
                   zorder=4)


def scaling_plot(rows, path, title=None):
    """Cost per step vs segment count, log-log, one line per engine/solver, O(n) guide."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    series = {}
    for r in rows:
        series.setdefault(r['series'], []).append((r['n_segments'], r['cpu_us_per_step']))
    styles = {'RK4 banded': ('tab:blue', 'o'), 'SE banded': ('tab:orange', 'o'),
              'RATTLE banded': ('tab:green', 'o'),
              'MuJoCo RK4': ('tab:purple', 'P')}
    for name, pts in series.items():
        pts.sort()
        c, m = styles.get(name, ('gray', 'o'))
        ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=m, color=c, label=name)
    ref = series.get('RK4 banded')
    if ref:
        n_hi, c_hi = ref[-1]
        ns = np.array([1.0, n_hi])
        ax.plot(ns, c_hi * ns / n_hi, 'k:', lw=1.0, label='O(n) guide')
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('segments in the chain')
    ax.set_ylabel('CPU µs per internal step')
    ax.grid(True, which='both', lw=0.3, alpha=0.5)
    ax.legend(fontsize=8)
    ax.set_title(title or 'Cost per step vs segment count')
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def mujoco_plot(rows, path):
    """Left: tip RMS vs CPU per simulated second per segment count, ours vs MuJoCo.
    Right: CPU per step vs segment count."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 5.2))
    ns = sorted({r['n_segments'] for r in rows})
    cmap = plt.get_cmap('viridis')
    for i, n in enumerate(ns):
        col = cmap(i / max(len(ns) - 1, 1))
        for eng, ls, mk in (('ours', '-', 'o'), ('mujoco', '--', 'P')):
            rs = sorted([r for r in rows if r['n_segments'] == n and r['engine'] == eng
                         and r['stable'] and np.isfinite(r['tip_rms_mm'])],
                        key=lambda r: r['cpu_s_per_sim_s'])
            if rs:
                label = f'{"ours RK4" if eng == "ours" else "MuJoCo RK4"} N={n}'
                a1.plot([r['cpu_s_per_sim_s'] for r in rs], [r['tip_rms_mm'] for r in rs], ls=ls,
                        marker=mk, color=col, label=label)
                for r in rs:
                    a1.annotate(r['dt_label'], (r['cpu_s_per_sim_s'], r['tip_rms_mm']), fontsize=6,
                                textcoords='offset points', xytext=(3, 2))
    for eng, c, mk in (('ours', 'tab:blue', 'o'), ('mujoco', 'tab:green', 'P')):
        per_n = {}
        for r in rows:
            if r['engine'] == eng:
                per_n.setdefault(r['n_segments'], []).append(r['cpu_us_per_step'])
        xs = sorted(per_n)
        a2.plot(xs, [np.median(per_n[x]) for x in xs], marker=mk, color=c,
                label='ours RK4 (banded)' if eng == 'ours' else 'MuJoCo RK4')
    for a in (a1, a2):
        a.set_xscale('log')
        a.set_yscale('log')
        a.grid(True, which='both', lw=0.3, alpha=0.5)
    a1.set_xlabel('CPU seconds per simulated second')
    a1.set_ylabel('tip RMS error (mm)')
    a1.set_title('moving-head ponytail: error vs cost (labels: dt)')
    a1.legend(fontsize=6.5)
    a2.set_xlabel('segments')
    a2.set_ylabel('CPU µs per step')
    a2.set_title('cost per step')
    a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def energy_plot(series, path, title=None):
    """Relative energy (E - E0)/(E0 - E_rest) over time, one line per setting."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 5))
    for label, (t, de) in series.items():
        ax.plot(t, de, lw=0.8, label=label)
    ax.set_xlabel('time (s)')
    ax.set_ylabel('(E - E0) / (E0 - E_rest)')
    ax.set_yscale('symlog', linthresh=1e-6)
    ax.grid(True, which='both', lw=0.3, alpha=0.5)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(title or 'Energy drift, still anchor, no damping')
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
