"""
The report's figures, drawn with matplotlib (Agg) and returned as inline SVG text.

Each function takes plain numbers (the report page gathers them from the result) and returns
one `<svg>` element: no file, no network, text kept as text (svg.fonttype 'none') so the page
stays small and searchable.
"""

import io

import numpy as np

USED, NOISY, REJECTED = '#3b7dd8', '#e8a33d', '#d64541'
AXIS_COLOURS = ('#d64541', '#3aa655', '#3b7dd8')   # x red, y green, z blue (RViz's)


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    # text.parse_math off: a frame name with $ in it is a name, not TeX (it had raised)
    matplotlib.rcParams.update({'svg.fonttype': 'none', 'font.size': 9, 'text.parse_math': False,
                                'axes.spines.top': False, 'axes.spines.right': False})
    from matplotlib import pyplot
    return pyplot


def svg_of(figure):
    """Return the SVG element of a matplotlib figure (and close it)."""
    pyplot = _pyplot()
    text = io.StringIO()
    figure.savefig(text, format='svg', bbox_inches='tight')
    pyplot.close(figure)
    svg = text.getvalue()
    return svg[svg.index('<svg'):]   # without the XML prolog and doctype: inline in HTML


def sample_residuals(rotation_deg, translation_mm, state, thresholds):
    """
    Bars of each sample's leave-one-out prediction error (deg, mm), coloured by state.

    state: per sample 'used', 'noisy' (down-weighted) or 'rejected'; thresholds: the
    validation's (max_rotation_deg, max_translation_mm), drawn as lines. A sample without a
    prediction (NaN: a rejected one, outside the leave-one-out) is a shaded column.
    """
    pyplot = _pyplot()
    colours = [{'used': USED, 'noisy': NOISY, 'rejected': REJECTED}[s] for s in state]
    index = np.arange(len(state))
    figure, axes = pyplot.subplots(2, 1, figsize=(8, 3.6), sharex=True)
    for ax, values, limit, unit in ((axes[0], rotation_deg, thresholds[0], 'deg'),
                                    (axes[1], translation_mm, thresholds[1], 'mm')):
        ax.bar(index, np.nan_to_num(values), color=colours, width=0.8)
        for k in np.flatnonzero(np.isnan(values)):
            ax.axvspan(k - 0.4, k + 0.4, color=colours[k], alpha=0.3, linewidth=0)
        ax.axhline(limit, color='#555555', linestyle='--', linewidth=0.8)
        ax.set_ylabel(f'prediction error ({unit})')
    axes[1].set_xlabel('sample')
    handles = [pyplot.Rectangle((0, 0), 1, 1, color=c) for c in (USED, NOISY, REJECTED)]
    axes[0].legend(handles, ['used', 'down-weighted (noisy)', 'rejected'], loc='upper right',
                   frameon=False, ncol=3)
    return svg_of(figure)


def convergence(counts, rotation_deg, uncertainty_deg, translation_mm, uncertainty_mm):
    """Distance of each prefix estimate from the final one, with its reported uncertainty."""
    pyplot = _pyplot()
    figure, axes = pyplot.subplots(1, 2, figsize=(8, 2.6))
    for ax, values, sigma, unit in ((axes[0], rotation_deg, uncertainty_deg, 'deg'),
                                    (axes[1], translation_mm, uncertainty_mm, 'mm')):
        ax.plot(counts, values, 'o-', color=USED, markersize=3, label='from the final answer')
        ax.fill_between(counts, 0, sigma, color=USED, alpha=0.15, label='reported uncertainty')
        ax.set_xlabel('samples')
        ax.set_ylabel(unit)
    axes[0].set_title('rotation', fontsize=9)
    axes[1].set_title('translation', fontsize=9)
    axes[0].legend(frameon=False, fontsize=8)
    return svg_of(figure)


def axis_coverage(axes_link, angles_deg, weakest_axis, frame='link'):
    """
    Where the motions' rotation axes point (in `frame`), and how large the motions are.

    An axis and its opposite excite the same direction: each is drawn with z >= 0, in the two
    views x-y and x-z; the least determined axis is marked.
    """
    pyplot = _pyplot()
    axes_link = np.asarray(axes_link, float).reshape(-1, 3)
    flipped = np.where(axes_link[:, 2:] < 0, -axes_link, axes_link)
    weakest = np.asarray(weakest_axis, float)
    weakest = -weakest if weakest[2] < 0 else weakest
    figure, (top, side, sizes) = pyplot.subplots(1, 3, figsize=(9, 2.8))
    for ax, (i, j), name in ((top, (0, 1), 'x-y'), (side, (0, 2), 'x-z')):
        ax.add_patch(pyplot.Circle((0, 0), 1, fill=False, color='#999999', linewidth=0.8))
        ax.scatter(flipped[:, i], flipped[:, j], s=10, color=USED)
        ax.scatter([weakest[i]], [weakest[j]], s=60, marker='x', color=REJECTED,
                   label='least determined')
        ax.set_xlim(-1.1, 1.1)
        ax.set_ylim(-1.1, 1.1)
        ax.set_aspect('equal')
        ax.set_title(f'motion axes, {frame} {name}', fontsize=9)
        ax.set_xlabel('xyz'[i])
        ax.set_ylabel('xyz'[j])
    top.legend(frameon=False, fontsize=8, loc='lower left')
    sizes.hist(angles_deg, bins=min(20, max(5, len(angles_deg) // 3)), color=USED)
    sizes.set_title('motion angles', fontsize=9)
    sizes.set_xlabel('deg')
    return svg_of(figure)


def mount_views(matrix, translation, parent, child):
    """Draw the mounting in two views (x-y from above, x-z from the side): both frames' axes."""
    pyplot = _pyplot()
    R, t = np.asarray(matrix, float), np.asarray(translation, float)
    length = max(0.3 * float(np.linalg.norm(t)), 0.02)
    figure, axes = pyplot.subplots(1, 2, figsize=(8, 3.2))
    for ax, (i, j), name in ((axes[0], (0, 1), 'from above (x-y)'),
                             (axes[1], (0, 2), 'from the side (x-z)')):
        for origin, rotation, label in ((np.zeros(3), np.eye(3), parent), (t, R, child)):
            for k in range(3):
                tip = origin + length * rotation[:, k]
                ax.annotate('', (tip[i], tip[j]), (origin[i], origin[j]),
                            arrowprops={'arrowstyle': '->', 'color': AXIS_COLOURS[k],
                                        'linewidth': 1.5})
            ax.text(origin[i], origin[j], f' {label}', fontsize=8, va='top')
        points = np.array([[0, 0, 0], t, *(length * np.eye(3)), *(t + length * R.T)])
        low, high = points.min(axis=0) - length * 0.5, points.max(axis=0) + length * 0.5
        ax.set_xlim(low[i], high[i])
        ax.set_ylim(low[j], high[j])
        ax.set_aspect('equal')
        ax.set_xlabel(f'{"xyz"[i]} (m, {parent})')
        ax.set_ylabel(f'{"xyz"[j]} (m)')
        ax.set_title(name, fontsize=9)
    return svg_of(figure)
