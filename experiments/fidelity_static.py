"""Static fidelity against beam theory (issue 13): reports/fidelity_static.{md,json}.

For each vertex count, a horizontal cantilever (EI 3e-4 N m^2, free length 0.3 m, default hair
density 2e-4 kg/m and EA 20 N: sag 2.2 % of L) clamped at its kinematic root, its static tip
deflection over Euler-Bernoulli w L^4 / (8 EI) and over the elastica, with the simulator's
bending and with the plain Voronoi length at the clamp (before issue 13), and the observed
convergence order; and a hanging strand's largest edge-strain error against g (mass below) / EA
and its elongation over rho g L^2 / (2 EA).  Definitions in hairexp/evaluation/fidelity_static.py.
Usage: python -m experiments.fidelity_static [--vertices 10 20 40 80] [--report NAME]
"""

from __future__ import annotations

import argparse

from hairexp.app.report import header, write_report
from hairexp.evaluation import fidelity_static as fs

from experiments.common import add_report_option, check_reports, md_table, strand_vertices


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vertices", type=strand_vertices, nargs="+", default=[10, 20, 40, 80])
    add_report_option(ap, "fidelity_static")
    args = ap.parse_args(argv)
    check_reports(ap, args.report)
    ns = args.vertices
    rows = {c: fs.table(ns, clamp=c) for c in fs.CLAMPS}
    order = {c: fs.observed_order(ns, [r["sag_ratio_elastica"] - 1.0 for r in rows[c]]) for c in fs.CLAMPS}
    new, old = rows["free_half"], rows["voronoi"]
    cells = []
    for i, n in enumerate(ns):
        o_new = f"{order['free_half'][i - 1]:.2f}" if i else ""
        o_old = f"{order['voronoi'][i - 1]:.2f}" if i else ""
        cells.append([n, f"{old[i]['sag_ratio']:.4f}", f"{new[i]['sag_ratio']:.4f}", f"{old[i]['sag_ratio_elastica']:.4f}",
                      f"{new[i]['sag_ratio_elastica']:.4f}", o_old, o_new, f"{new[i]['hanging_strain_error']:.1e}",
                      f"{new[i]['hanging_elongation_ratio'] - 1:.1e}"])
    r0 = new[0]
    md = header("Static fidelity against beam theory (issue 13)")
    md += (f"Cantilever: EI {fs.EI:g} N m^2, free length {fs.FREE_LENGTH:g} m, density {fs.LINEAR_DENSITY:g} kg/m, "
           f"EA {fs.EA:g} N; Euler-Bernoulli tip deflection {1e3 * r0['euler_bernoulli']:.4f} mm "
           f"({100 * r0['euler_bernoulli'] / fs.FREE_LENGTH:.2f} % of L), elastica {1e3 * r0['elastica']:.4f} mm. "
           "Sag ratio = simulated tip deflection / reference; 'before' = the plain Voronoi length at the clamp "
           "element, 'after' = the free half-edge (the simulator's). Order: of the error against the elastica "
           "between this row and the previous one. Hanging strand: max |strain - g m_below / EA| over the largest "
           "strain, and elongation / (rho g L^2 / 2 EA) - 1.\n\n")
    md += md_table(["vertices", "sag / E-B before", "sag / E-B after", "sag / elastica before",
                    "sag / elastica after", "order before", "order after", "hanging strain error",
                    "hanging elongation error"], cells)
    print(md)
    write_report(args.report, md, {"vertices": ns, "rows": rows, "order": order})


if __name__ == "__main__":
    from experiments.common import run_script

    run_script(main)
