"""A convergence and work-precision study in a script: quadratic MPM with and
without reconstruction against FEM on S1; writes CSV, Markdown and PNGs.

    python examples/study.py
"""
from skfem_mpm.study import convergence, fastest_to, markdown_table, write_report


def main(cells=(8, 16, 32), out="study-output", executor=None):
    methods = ["mpm-p2-consistent", "mpm-p2-consistent-spline", "fem-p2-consistent"]
    records = convergence("vibrating-string", methods, cells, ppc=4, scheme="cd", cfl=0.1,
                          executor=executor)
    print(markdown_table(records))
    print("fastest to 1e-4:", fastest_to(records, 1e-4))
    write_report(records, out)
    return records


if __name__ == "__main__":
    main()
