"""``rtsgt analyze`` (per-source noise analysis and figures) and ``rtsgt report`` (HTML report)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.choices import DEFAULT_BINS_M
from rtsgt.io.output_dir import OutputDir, check_output_file, record_files

if TYPE_CHECKING:
    from rich.console import Console

    from rtsgt.report.analysis import Analysis

#: ``--bins``'s default, the analysis's default bins (:data:`rtsgt.choices.DEFAULT_BINS_M`).
DEFAULT_BINS = ",".join(f"{b:g}" for b in DEFAULT_BINS_M)
_BINS_HELP = ("Lower edges of the range bins in m, comma separated; the last bin is open "
              "(default: the paper's 0-75, 75-150, > 150 m).")
_ENGINE_HELP = ("Pose engine for the per-source poses: mc, ut or linear (default: linear, the "
                "first-order split; mc: the run's Monte Carlo, 30x slower).")


def _mm(x) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.3g}"


def print_analysis(analysis: Analysis, console: Console | None = None) -> None:
    """The per-source medians next to the paper's, and the pose uncertainty per source."""
    from rich import box
    from rich.console import Console

    from rtsgt.cli.tables import TextTable
    from rtsgt.report.analysis import PAPER_CITATION

    console = console or Console()
    a = analysis
    bins = [lab.replace(" m", "m").replace("> ", ">") for lab in a.bin_labels]
    table = TextTable(f"{a.name}: prism covariance, median sqrt(||Sigma||_F) (mm)",
                      ("source", "all", "paper", *[c for lab in bins for c in (lab, "paper")]),
                      box=box.SIMPLE_HEAD,
                      caption="range bins: " + ", ".join(
                          f"{lab} n={c} ({100 * sh:.0f} %)"
                          for lab, c, sh in zip(a.bin_labels, a.bin_counts, a.bin_shares,
                                                strict=True)) + f"; {a.n_measurements} measurements")
    for r in a.table_rows():
        cells = [r["source"], _mm(r["median_mm"]), _mm(r["paper_median_mm"])]
        for b in r["bins"]:
            cells += [_mm(b["median_mm"]), _mm(b["paper_median_mm"])]
        table.add_row(*(f"[bold]{c}[/bold]" if r["source"] == "all" else c for c in cells))
    table.print(console)
    console.print(f"[dim]paper: {PAPER_CITATION}[/dim]")
    measure = "sqrt(trace)" if a.pose_measure == "sqrt_trace" else "sqrt(largest eigenvalue)"
    pose = TextTable(f"pose uncertainty per source, median of {a.pose_t.size} poses",
                     ("source", "translation (mm)", "rotation (mrad)"), box=box.SIMPLE_HEAD,
                     caption=f"{a.engine} engine; {measure} of each 3x3 block")
    for r in a.pose_rows():
        cells = (r["source"], _mm(r["translation_mm"]), _mm(r["rotation_mrad"]))
        pose.add_row(*(f"[bold]{c}[/bold]" if r["source"] == "all" else c for c in cells))
    pose.print(console)


def run_analyze(run_dir: Path, *, bins: str = DEFAULT_BINS, out: Path | None = None,
                engine: str | None = None, samples: int | None = None,
                pose_measure: str = "sqrt_trace", figures: bool = True,
                formats: tuple[str, ...] = ("png", "svg"),
                force: bool = False) -> tuple[Analysis, list[Path]]:
    """Analyse a run directory, write the figures and ``analysis.json`` into ``out`` (default
    ``RUN_DIR/analysis``, whole or not at all); returns the analysis and the files."""
    from rtsgt.io.run_dir import read_run
    from rtsgt.report.analysis import analyze
    from rtsgt.report.figures import draw_all, save_figures

    folder = Path(run_dir) / "analysis" if out is None else Path(out)
    output = OutputDir(folder, "analysis", force=force, inputs=[run_dir])
    data = read_run(run_dir)
    analysis = analyze(data, bins=bins, engine=engine, samples=samples, pose_measure=pose_measure)
    with output as tmp:
        names: list[str] = []
        if figures:
            names += [p.name for p in save_figures(draw_all(data, analysis), tmp, formats)]
        (tmp / "analysis.json").write_text(json.dumps(analysis.to_dict(), indent=2) + "\n",
                                           encoding="utf-8")
        names.append("analysis.json")
    return analysis, [output.final / n for n in names]


def register(app: typer.Typer) -> None:
    """Add ``rtsgt analyze`` and ``rtsgt report`` to the application."""

    @app.command("analyze")
    def analyze_command(
        run_dir: Path = typer.Argument(..., metavar="RUN_DIR",
                                       help="Output directory of `rtsgt run`."),
        bins: str = typer.Option(DEFAULT_BINS, "--bins", help=_BINS_HELP),
        out: Path = typer.Option(None, "--out", "-o",
                                 help="Folder for the figures and analysis.json "
                                      "(default: RUN_DIR/analysis)."),
        as_json: bool = typer.Option(False, "--json",
                                     help="Print one JSON object instead of the tables."),
        engine: str = typer.Option(None, "--engine", help=_ENGINE_HELP),
        samples: int = typer.Option(None, "--samples", min=10,
                                    help="Monte Carlo samples (default: the run's)."),
        pose_measure: str = typer.Option(
            "sqrt_trace", "--pose-measure",
            help="Size of a 3x3 pose covariance block: sqrt_trace or max_std "
                 "(sqrt of the largest eigenvalue)."),
        no_figures: bool = typer.Option(False, "--no-figures", help="Write no figures."),
        figure_format: str = typer.Option("png,svg", "--figure-format", metavar="FORMATS",
                                          help="Figure formats, comma separated: png, svg, pdf."),
        old_formats: str = typer.Option(None, "--formats", hidden=True,
                                        help="The old spelling of --figure-format."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace an earlier output of rtsgt at --out (never a "
                                        "directory holding anything else)."),
    ) -> None:
        """Per-source noise analysis of a run, next to the paper's medians, with figures."""
        from rich.console import Console

        option = "--figure-format"
        if old_formats is not None:  # the spelling of earlier versions, kept for scripts
            if figure_format != "png,svg":
                raise typer.BadParameter("give --figure-format only (--formats is its old "
                                         "spelling)", param_hint="--formats")
            figure_format, option = old_formats, "--formats"
        fmts = tuple(f.strip().lower() for f in figure_format.split(",") if f.strip())
        bad = [f for f in fmts if f not in ("png", "svg", "pdf")]
        if bad or not fmts:
            raise typer.BadParameter(f"expected png, svg or pdf, got {figure_format!r}",
                                     param_hint=option)
        analysis, written = run_analyze(run_dir, bins=bins, out=out, engine=engine,
                                        samples=samples, pose_measure=pose_measure,
                                        figures=not no_figures, formats=fmts, force=force)
        if as_json:
            d = analysis.to_dict()
            d["files"] = [str(p) for p in written]
            typer.echo(json.dumps(d))
            return
        print_analysis(analysis)
        folder = written[-1].parent
        what = "analysis.json" if no_figures else "figures and analysis.json"
        Console(stderr=True).print(f"{what} in {folder}", highlight=False, soft_wrap=True)

    @app.command("report")
    def report_command(
        run_dir: Path = typer.Argument(..., metavar="RUN_DIR",
                                       help="Output directory of `rtsgt run`."),
        out: Path = typer.Option(None, "--out", "-o",
                                 help="HTML file to write (default: RUN_DIR/report.html)."),
        open_: bool = typer.Option(False, "--open",
                                   help="Open the report in the system's web browser."),
        bins: str = typer.Option(DEFAULT_BINS, "--bins", help=_BINS_HELP),
        engine: str = typer.Option(None, "--engine", help=_ENGINE_HELP),
        samples: int = typer.Option(None, "--samples", min=10,
                                    help="Monte Carlo samples (default: the run's)."),
        figure_format: str = typer.Option("svg", "--figure-format", metavar="FORMAT",
                                          help="Format of the embedded figures: svg or png."),
    ) -> None:
        """Write a single self-contained HTML report of a run (opens offline)."""
        import webbrowser

        from rich.console import Console

        from rtsgt.io.run_dir import read_run
        from rtsgt.report.analysis import analyze
        from rtsgt.report.html import is_report_html, write_report_file

        if figure_format not in ("svg", "png"):
            raise typer.BadParameter(f"expected svg or png, got {figure_format!r}",
                                     param_hint="--figure-format")
        path = Path(run_dir) / "report.html" if out is None else Path(out)
        check_output_file(path, option="--out", written_by_rtsgt=is_report_html)
        data = read_run(run_dir)
        analysis = analyze(data, bins=bins, engine=engine, samples=samples)
        info = write_report_file(data, analysis, path, figure_format=figure_format)
        record_files(path.parent, [path])  # part of the run directory's output, if it is one
        err = Console(stderr=True)
        typer.echo(str(info.path))
        if open_:
            # the system's browser (the BROWSER environment variable overrides the choice)
            if not webbrowser.open(info.path.resolve().as_uri()):
                err.print(f"could not start a browser; open {info.path.resolve().as_uri()} "
                          "yourself")
