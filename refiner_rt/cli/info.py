"""``refiner-rt info MODEL.onnx``: print a model's metadata contract, graph inputs/outputs and size."""

from __future__ import annotations

import json
from pathlib import Path

import click


def count_parameters(path: Path) -> int | None:
    """Number of weights in the model's initializers (needs the ``onnx`` package; None without it)."""
    try:
        import onnx
    except ModuleNotFoundError:
        return None
    model = onnx.load(str(path), load_external_data=False)
    total = 0
    for init in model.graph.initializer:
        n = 1
        for d in init.dims:
            n *= d
        total += n
    return total


def describe(path: Path) -> dict:
    """Everything ``info`` prints, as a dict (metadata, inputs, outputs, file size, parameters)."""
    from refiner_rt.session import RefinerSession

    sess = RefinerSession(path, threads=1)
    params = count_parameters(path)
    if params is None and "num_parameters" in sess.metadata:
        params = int(sess.metadata["num_parameters"])
    return {
        "path": str(path),
        "file_size_bytes": path.stat().st_size,
        "parameters": params,
        "metadata": sess.metadata,
        "inputs": [{"name": i.name, "type": i.type, "shape": list(i.shape)} for i in sess.get_inputs()],
        "outputs": [{"name": o.name, "type": o.type, "shape": list(o.shape)} for o in sess.get_outputs()],
    }


@click.command("info")
@click.argument("model", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def info_cmd(model: Path, as_json: bool):
    """Print MODEL's metadata contract, inputs/outputs, parameter count and file size."""
    from refiner_rt.errors import ModelError

    try:
        d = describe(model)
    except ModelError as exc:  # names the file already
        raise click.ClickException(str(exc)) from None
    except ValueError as exc:
        raise click.ClickException(f"{model}: {exc}") from None
    if as_json:
        click.echo(json.dumps(d, indent=2))
        return
    click.echo(f"model: {d['path']}")
    click.echo(f"file size: {d['file_size_bytes'] / 1e6:.2f} MB")
    click.echo(f"parameters: {d['parameters'] if d['parameters'] is not None else 'unknown (install onnx to count)'}")
    click.echo("inputs:")
    for i in d["inputs"]:
        click.echo(f"  {i['name']:<8} {i['type']:<16} {i['shape']}")
    click.echo("outputs:")
    for o in d["outputs"]:
        click.echo(f"  {o['name']:<8} {o['type']:<16} {o['shape']}")
    click.echo("metadata:")
    for k, v in d["metadata"].items():
        click.echo(f"  {k:<20} {json.dumps(v) if isinstance(v, list) else v}")
