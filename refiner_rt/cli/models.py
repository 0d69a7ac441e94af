"""``refiner-rt models``: the table of the refiners shipped in the package (torch-free)."""

from __future__ import annotations

import json

import click

from refiner_rt.pretrained import WEIGHTS_DIR, pretrained_models

__all__ = ["models_cmd"]


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _cascade(m, key: str):
    """The cascade's ``key`` (``mean_deg``, ``drift_mean_deg``) on the card's fresh renders, or None."""
    return m.fine.get("card", {}).get("cascade", {}).get("cascade", {}).get(key)


@click.command("models")
@click.option("--json", "as_json", is_flag=True, help="Print the model-card data as JSON instead of a table.")
def models_cmd(as_json):
    """List the pretrained refiners: object, architecture, file size, held-out-scene error, INT8 speed.

    Errors are the INT8 model's mean geodesic error (degrees) on rendered scenes held out from its training,
    from coarse inputs drawn U(0, 30) degrees around the truth, and on real camera frames (with the drift: how
    far a perfect input pose is moved); speed is refinements/s at batch 1 on one core
    through the full refine() path (see refiner_rt/weights/MODELS.md for the machine and the commands).
    Load one with RefinerSession.pretrained("<object>").
    """
    try:
        models = pretrained_models()
    except (ValueError, KeyError, TypeError) as exc:
        raise click.ClickException(f"cannot list the pretrained models: {exc}") from None
    if as_json:
        click.echo(json.dumps([{"object_id": m.object_id, "arch": m.arch, "version": m.version, "files": m.files,
                                "heldout": m.heldout, "real": m.real, "config": m.config, "card": m.card,
                                "stages": m.stages, "fine": m.fine} for m in models], indent=1))
        return
    if not models:
        click.echo("No pretrained models ship in this installation.")
        return
    head = ("object", "arch", "version", "INT8 MB", "fp32 MB", "held-out mean", "median", "input", "real frames",
            "drift", "INT8 /s", "stages", "cascade", "cascade drift")
    rows = []
    for m in models:
        sizes = {k: (WEIGHTS_DIR / f).stat().st_size / 1e6 for k, f in m.files.items() if (WEIGHTS_DIR / f).is_file()}
        rows.append((m.object_id, m.arch, m.version, _fmt(sizes.get("int8"), ".1f"), _fmt(sizes.get("fp32"), ".1f"),
                     _fmt(m.heldout.get("mean_deg"), ".2f"), _fmt(m.heldout.get("median_deg"), ".2f"),
                     _fmt(m.heldout.get("input_mean_deg"), ".2f"), _fmt(m.real.get("mean_deg"), ".2f"),
                     _fmt(m.real.get("drift_mean_deg"), ".2f"), _fmt(m.card.get("int8_refinements_per_s"), ",.0f"),
                     "+".join(m.stages), _fmt(_cascade(m, "mean_deg"), ".2f"), _fmt(_cascade(m, "drift_mean_deg"), ".2f")))
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(len(head))]
    line = lambda r: "  ".join(str(c).ljust(w) if i == 0 else str(c).rjust(w) for i, (c, w) in enumerate(zip(r, widths)))
    click.echo(line(head))
    for r in rows:
        click.echo(line(r))
    split = models[0].heldout.get("split", "held-out scenes")
    real = next((m.real for m in models if m.real), None)
    click.echo(f"\nErrors in degrees on rendered {split}, inputs U(0, 30)"
               + (f"; real frames: every instance in the real camera frames of {real.get('data')} (same inputs), "
                  "drift: how far a perfect input pose is moved there" if real else "")
               + ". Load one with RefinerSession.pretrained(\"<object>\") and pass the camera intrinsics K to refine()."
               + (" Stages coarse+fine: a fine refiner ships too (RefinerCascade.pretrained(\"<object>\") runs both); "
                  "cascade: its mean from the same inputs and its drift, on the fresh renders of the card"
                  if any(m.fine for m in models) else ""))
