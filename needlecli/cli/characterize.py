"""``needle characterize-sensor CONFIG``: the error of a config's image pipelines on repeated frames of
chosen poses (the multi-rate UKF paper's characterisation), as tables, and the Gaussian ``sigma`` that matches it."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import fail, progress_bar, setup_logging, user_errors


@user_errors
def characterize_sensor(
    config: Path = typer.Argument(..., help="Experiment config with sensors that use pipeline: image."),
    sensor: str = typer.Option(None, "--sensor", help="Only this sensor (default: every image sensor)."),
    repeats: int = typer.Option(20, "--repeats", "-r", min=2, help="Frames per pose (the multi-rate UKF paper: 20)."),
    seed: int = typer.Option(0, "--seed", "-s", min=0, help="Seed of the frames' noise."),
    outlier: float = typer.Option(None, "--outlier", min=0.0, help="Error (mm) counted as an outlier (default: 5 pixels)."),
    mode: str = typer.Option("tracking", "--mode", help="3D ultrasound region: tracking (around a prediction) or search."),
    out: Path = typer.Option(None, "--out", "-o", help="Folder for the tables (default: CONFIG_characterization/ beside the config)."),
    format_: str = typer.Option("md,csv", "--format", "-f", help="Table formats: md, csv, tex."),
    set_: list[str] = typer.Option([], "--set", help="Override a config key: --set sensors.0.image.voxel=0.5"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar; print nothing but errors."),
) -> None:
    """Measure each image pipeline's bias, spread, outlier and lost-frame rates against what its quality
    depends on, and print the Gaussian sensor settings that match it.

    Example: needle characterize-sensor configs/examples/imaging_us2d.yaml --repeats 10
    """
    import yaml

    from needlecli.experiments.config.load import load_config
    from needlecli.reports.tables import to_markdown, write_table
    from needlecli.sensors.imaging.characterize import characterize_sensors

    setup_logging(quiet)
    if mode not in ("tracking", "search"):
        fail(f"--mode: unknown mode {mode!r}; use tracking or search")
    formats = [f.strip() for f in format_.split(",") if f.strip()]
    for f in formats:
        if f not in ("md", "csv", "tex"):
            fail(f"--format: unknown format {f!r}; use md, csv, tex")
    from needlecli.io.atomic import check_output_dir

    cfg, _ = load_config(config, overrides=set_, memory=False)  # frames of chosen poses, not the experiment
    out_dir = out if out is not None else config.parent / f"{config.stem}_characterization"
    check_output_dir(out_dir, what="the characterization tables")
    with progress_bar(not quiet) as bar:
        results = characterize_sensors(cfg, sensor=sensor, repeats=repeats, seed=seed, outlier=outlier, mode=mode,
                                       source=str(config), progress=bar)
    for r in results:
        caption = (f"{r.sensor} ({r.device}): error of the image pipeline over {repeats} frames per pose "
                   f"({mode}); bias and std over the frames that are not outliers")
        paths = write_table(r.table, out_dir / f"{cfg.name}_{r.sensor}_characterization", formats, caption=caption)
        if not quiet:
            typer.echo(f"## {r.sensor} ({r.device})\n")
            typer.echo(to_markdown(r.table))
            if r.suggestion:
                typer.echo("\nGaussian settings matching it (pipeline: gaussian):")
                typer.echo(yaml.safe_dump(r.suggestion, default_flow_style=True, sort_keys=False).strip())
            typer.echo(f"\ntables: {', '.join(str(p) for p in paths)}\n")
