"""``rtsgt simulate``: write a simulated deployment with known truth (:mod:`rtsgt.simulation`)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from rtsgt.choices import REALITY_EFFECTS, SIMULATION_PRESETS
from rtsgt.cli.common import usage_error
from rtsgt.io.output_dir import check_target

if TYPE_CHECKING:
    from rich.console import Console


def run_simulate(
    out_dir: Path, *, seed: int = 0, duration: float | None = None, stations: int = 3,
    force: bool = False, reality: tuple[str, ...] = (), preset: str | None = None,
):
    """Simulate and write a deployment; returns ``(sim, path to deployment.toml)``.
    ``duration`` s (None: 600, or the ``preset``'s); ``reality``: effects switched on."""
    from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
    from rtsgt.simulation.presets import preset_config
    from rtsgt.simulation.reality import RealityEffects

    unknown = [e for e in reality if e not in REALITY_EFFECTS]
    if unknown:
        raise usage_error(f"Expected reality effects among {', '.join(REALITY_EFFECTS)}, got "
                          f"{', '.join(map(repr, unknown))}", "--reality")
    if preset is not None and preset not in SIMULATION_PRESETS:
        raise usage_error(f"Expected a preset among {', '.join(SIMULATION_PRESETS)}, got "
                          f"{preset!r}", "--preset")
    check_target(out_dir, force=force)  # refuse early, before spending time on the simulation
    try:
        if preset is None:
            config = SimulationConfig(n_stations=stations,
                                      reality=RealityEffects(**dict.fromkeys(reality, True)),
                                      **({} if duration is None else {"duration_s": duration}))
        else:
            config = preset_config(preset, duration_s=duration, n_stations=stations,
                                   reality=tuple(reality))
    except ValueError as exc:
        raise usage_error(str(exc), "--duration") from None
    sim = simulate_deployment(config, int(seed))  # an int seed is recorded in the result
    toml = write_deployment(sim, out_dir, overwrite=force)
    return sim, toml


def _print_summary(sim, toml: Path, console: Console) -> None:
    from rtsgt.cli.tables import TextTable

    out = toml.parent
    table = TextTable(f"simulated deployment written to {out}", ("file", "content", "size"),
                      right=(False, False, True))

    def size(name: str) -> str:
        n = (out / name).stat().st_size
        return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"

    tr = sim.truth

    def drift(sid: str) -> str:
        if tr.field is None:
            return ""
        k = tr.field.station_ids.index(sid)
        return f", drifting {3.6e6 * tr.field.clock_drift_s_per_s[k]:+.1f} ms/h (field)"

    for obs in sim.observations:
        o = tr.observations[obs.station]
        rng = (o.d.min() + tr.additive_constant, o.d.max() + tr.additive_constant)
        name = f"prism{obs.prism}.csv"
        table.add_row(name,
                      f"station {obs.station} -> prism {obs.prism}: {len(obs)} measurements, "
                      f"range {rng[0]:.0f}-{rng[1]:.0f} m, clock offset "
                      f"{tr.clock_offset_s[obs.station] * 1e3:.3f} ms" + drift(obs.station),
                      size(name))
    n_markers = len(set(sim.gcp.marker.tolist()))
    table.add_row("GCP.txt", f"{len(sim.gcp)} shots of {n_markers} markers", size("GCP.txt"))
    table.add_row("calibration_raw.csv",
                  f"static survey, {len(sim.survey.names)} points (prisms, GNSS)",
                  size("calibration_raw.csv"))
    table.add_row("weather.csv", f"{len(sim.weather_reported.t)} hourly records",
                  size("weather.csv"))
    table.add_row("truth.tum", f"T_world_body, {len(tr.t)} poses at "
                  f"{sim.config.truth_rate_hz:g} Hz", size("truth.tum"))
    table.add_row("truth_prisms.csv", "true prism positions (world)", size("truth_prisms.csv"))
    table.add_row("truth.json", "stations, clock offsets, reference points, config",
                  size("truth.json"))
    table.add_row("deployment.toml", "configuration for `rtsgt run`", size("deployment.toml"))
    table.print(console)
    console.print(f"next: rtsgt run {toml}")


def register(app: typer.Typer) -> None:
    """Add ``rtsgt simulate`` to the application."""

    @app.command("simulate")
    def simulate_command(
        out_dir: Path = typer.Argument(..., metavar="OUT_DIR",
                                       help="Directory to create with the deployment's files."),
        seed: int = typer.Option(0, "--seed", min=0, help="Seed of the random generator (>= 0)."),
        duration: float | None = typer.Option(
            None, "--duration", min=1.0, show_default=False,
            help="Length of the tracking session, s [default: 600; a preset's own: "
                 + ", ".join(f"{k} {v:g}" for k, v in SIMULATION_PRESETS.items()) + "]."),
        stations: int = typer.Option(3, "--stations", min=3,
                                     help="Number of stations (each tracks its own prism)."),
        force: bool = typer.Option(False, "--force",
                                   help="Replace OUT_DIR if it is an earlier output of rtsgt "
                                        "(never a directory holding anything else)."),
        reality: list[str] = typer.Option(
            [], "--reality", metavar="EFFECT",
            help="Switch a reality effect on at its default size (repeatable; see "
                 "docs/simulation.md): " + ", ".join(REALITY_EFFECTS) + "."),
        preset: str | None = typer.Option(
            None, "--preset", metavar="NAME",
            help="A named deployment (docs/simulation.md#the-field-hour-preset): "
                 + ", ".join(SIMULATION_PRESETS) + "; --reality adds to its effects."),
    ) -> None:
        """Simulate a deployment with known truth and write it as a real one's files."""
        from rich.console import Console

        sim, toml = run_simulate(out_dir, seed=seed, duration=duration, stations=stations,
                                 force=force, reality=tuple(reality), preset=preset)
        _print_summary(sim, toml, Console())
