"""The graph of a run as a picture: ``persona plan WORKFLOW --svg plan.svg`` or ``--html plan.html``.

One column per collection and per drive, one row per stage (in :data:`persona.dag.stages.STAGES`
order), each node coloured by its status in the store (:func:`persona.dag.graph.status`) and joined to
the nodes it reads. Hand-written SVG, self-contained: no script, no font or style fetched.
"""

from __future__ import annotations

import html

from .graph import DONE, FAILED, TO_RUN, Graph, Node
from .stages import STAGES

#: fill and outline of a node by its status
COLOURS = {DONE: ("#d9f2d9", "#2e7d32"), TO_RUN: ("#fff3cd", "#b8860b"), FAILED: ("#f8d7da", "#b00020")}
WIDTH, HEIGHT, GAP_X, GAP_Y, TOP, LEFT = 150, 26, 40, 14, 70, 20


def svg(graph: Graph, statuses: dict[Node, str], title: str = "") -> str:
    """The graph as one ``<svg>`` element: a ``<g class="node">`` per node, a ``<path class="edge">`` per edge."""
    columns = list(dict.fromkeys(node.target for node in graph.nodes))
    rows = {name: i for i, name in enumerate(STAGES)}
    used = sorted({rows[node.stage] for node in graph.nodes})
    row_of = {row: i for i, row in enumerate(used)}

    def at(node: Node) -> tuple[float, float]:
        return (LEFT + columns.index(node.target) * (WIDTH + GAP_X),
                TOP + row_of[rows[node.stage]] * (HEIGHT + GAP_Y))

    width = LEFT * 2 + len(columns) * (WIDTH + GAP_X) - GAP_X
    height = TOP + len(used) * (HEIGHT + GAP_Y) + 40
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="12">',
           '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="6" markerHeight="6" '
           'orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z" fill="#777"/></marker></defs>',
           f'<text x="{LEFT}" y="20" font-size="15" font-weight="bold">{_text(title)}</text>']
    for i, (state, (fill, line)) in enumerate(COLOURS.items()):  # the legend
        x = LEFT + i * 110
        out.append(f'<rect x="{x}" y="32" width="14" height="14" fill="{fill}" stroke="{line}"/>'
                   f'<text x="{x + 20}" y="44">{state}</text>')
    for target in columns:
        x = at(Node(graph.nodes[0].stage, target))[0]
        out.append(f'<text x="{x}" y="{TOP - 8}" font-weight="bold">{_text(target)} '
                   f'<tspan fill="#777" font-weight="normal">({graph.roles[target]})</tspan></text>')
    for a, b in graph.edges:
        (xa, ya), (xb, yb) = at(a), at(b)
        if xa == xb:  # within a column: down its left side
            d = f"M {xa + 12} {ya + HEIGHT} L {xb + 12} {yb}"
        else:  # across columns: from the right side of one to the left of the other
            x0, y0, x1, y1 = xa + WIDTH, ya + HEIGHT / 2, xb, yb + HEIGHT / 2
            d = f"M {x0} {y0} C {x0 + GAP_X} {y0}, {x1 - GAP_X} {y1}, {x1} {y1}"
        out.append(f'<path class="edge" d="{d}" fill="none" stroke="#999" marker-end="url(#arrow)">'
                   f'<title>{_text(f"{a} -> {b}")}</title></path>')
    for node in graph.nodes:
        x, y = at(node)
        state = statuses.get(node, TO_RUN)
        fill, line = COLOURS[state]
        stage = STAGES[node.stage]
        out.append(f'<g class="node" data-stage="{_text(node.stage)}" data-target="{_text(node.target)}" '
                   f'data-status="{state}"><title>{_text(f"{node}: {state} — {stage.makes} ({stage.per})")}</title>'
                   f'<rect x="{x}" y="{y}" width="{WIDTH}" height="{HEIGHT}" rx="5" fill="{fill}" stroke="{line}"/>'
                   f'<text x="{x + 8}" y="{y + 17}">{_text(node.stage)}</text></g>')
    out.append("</svg>")
    return "\n".join(out)


def page(graph: Graph, statuses: dict[Node, str], title: str) -> str:
    """A self-contained HTML page with the graph (:func:`svg`) and each status's count."""
    counts = {state: sum(1 for s in statuses.values() if s == state) for state in COLOURS}
    summary = ", ".join(f"{n} {state}" for state, n in counts.items())
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>{_text(title)}</title></head>\n"
            f"<body style=\"font-family: sans-serif\"><p>{len(graph.nodes)} stages: {summary}</p>\n"
            f"{svg(graph, statuses, title)}\n</body></html>\n")


def _text(value: str) -> str:
    return html.escape(str(value), quote=True)
