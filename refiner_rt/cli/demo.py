"""``refiner-rt demo``: refinement shown working, with the shipped models and the sample frames (torch-free)."""

from __future__ import annotations

import time
from pathlib import Path

import click
import cv2
import numpy as np

from refiner_rt.cli import check_picture_path, prepare_output, write_picture

__all__ = ["demo_cmd", "numbers_callback"]


def numbers_callback(count: int, names: str, positive: tuple[int, ...] = ()):
    """A click callback parsing ``count`` comma-separated finite numbers (``names`` says which, e.g. 'x1,y1,x2,y2')."""

    def parse(ctx, param, value):
        if value is None:
            return None
        try:
            out = [float(v) for v in value.split(",")]
        except ValueError:
            out = []
        if len(out) != count or not all(np.isfinite(out)):
            raise click.BadParameter(f"expected {count} comma-separated numbers {names}; got {value!r}")
        if any(out[i] <= 0 for i in positive):
            raise click.BadParameter(f"{', '.join(names.split(',')[i] for i in positive)} must be > 0; got {value!r}")
        return np.array(out, dtype=np.float64)

    return parse


@click.command("demo")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=Path("demo.png"), show_default=True,
              help="The picture to write (PNG).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the coarse rotations drawn around the truth.")
@click.option("--threads", type=click.IntRange(0), default=1, show_default=True,
              help="Threads per model (0: every core).")
@click.option("--image", "image_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Refine your own image instead of the samples; needs --box, --q, --K and --object.")
@click.option("--box", callback=numbers_callback(4, "x1,y1,x2,y2"), metavar="X1,Y1,X2,Y2",
              help="With --image: the object's box in pixels.")
@click.option("--q", "q", callback=numbers_callback(4, "w,x,y,z"), metavar="W,X,Y,Z",
              help="With --image: the coarse rotation, object to camera, quaternion wxyz (scalar first).")
@click.option("--K", "K", callback=numbers_callback(4, "fx,fy,cx,cy", positive=(0, 1)), metavar="FX,FY,CX,CY",
              help="With --image: the camera intrinsics in pixels.")
@click.option("--object", "object_id", metavar="YCB_ID", help="With --image: the object, e.g. 003_cracker_box.")
@click.option("--cascade", is_flag=True,
              help="Each object's coarse and fine refiners in turn (RefinerCascade) where a fine refiner ships: "
                   "about 0.5 degrees better from U(0, 30) inputs on fresh renders (3.30 against 3.82), and inputs "
                   "already close kept close, for eight to twelve network passes instead of one.")
def demo_cmd(out, seed, threads, image_path, box, q, K, object_id, cascade):
    """Refine coarse rotations with the shipped models and draw the result.

    Without --image: the sample frames in the package (rendered scenes that no shipped model trained on, with
    ground truth). Each object's coarse rotation is drawn U(0, 30) degrees around the truth, refined by the
    object's shipped INT8 model (with --cascade, its coarse and fine refiners) with the camera intrinsics, and
    compared with the truth. Prints a table of input and refined error (degrees) and time per refinement; the
    picture shows, per object, the truth (white), the coarse input (cyan) and the refined rotation (green) as
    outlines.

    With --image FILE --box X1,Y1,X2,Y2 --q W,X,Y,Z --K FX,FY,CX,CY --object ID: refines your image (BGR as read by
    OpenCV) and draws the coarse and refined outlines, placed from the box (the refiner estimates rotation only).
    The shipped models' object frame is the YCB google_16k scan frame.
    """
    extra = {"--box": box, "--q": q, "--K": K, "--object": object_id}
    if image_path is None:
        given = [name for name, v in extra.items() if v is not None]
        if given:
            raise click.UsageError(f"{', '.join(given)}: only with --image FILE (these options describe your own image)")
    else:
        missing = [name for name, v in extra.items() if v is None]
        if missing:
            raise click.UsageError(f"--image needs {', '.join(missing)} as well")
    check_picture_path(out)
    prepare_output(out, "'--out'")
    t0 = time.perf_counter()
    if image_path is None:
        _samples(out, seed, threads, cascade)
    else:
        _own_image(out, threads, image_path, box, q, K, object_id, cascade)
    click.echo(f"Wall time {time.perf_counter() - t0:.1f} s.")


def _refiner(object_id: str, threads: int, cascade: bool):
    """The shipped INT8 refiner of ``object_id``: its :class:`refiner_rt.RefinerCascade` with ``cascade`` where a
    fine refiner ships, else its :class:`refiner_rt.RefinerSession`."""
    from refiner_rt.refiner import load

    return load(object_id, cascade=cascade, int8=True, threads=threads)


def _samples(out: Path, seed: int, threads: int, cascade: bool = False) -> None:
    from refiner_rt import demo
    from refiner_rt.pretrained import pretrained_models

    frames = demo.load_samples()
    shipped = {m.object_id: m for m in pretrained_models()}
    if not shipped:
        raise click.ClickException("no pretrained models ship in this installation: nothing to demonstrate "
                                   "(`refiner-rt models` lists them)")
    seen = sorted({o.object_id for f in frames for o in f.objects})
    sessions = {obj: _refiner(obj, threads, cascade) for obj in seen if obj in shipped}
    refinements = demo.refine_samples(frames, sessions, seed=seed)
    models = "the shipped INT8 models"
    if cascade:
        with_fine = [obj for obj in sessions if "fine" in shipped[obj].stages]
        models = (f"the shipped INT8 cascades (coarse and fine refiners) of {len(with_fine)} objects"
                  + (", the coarse models of the rest" if len(with_fine) < len(sessions) else ""))
    click.echo(f"{len(refinements)} object instances in {len(frames)} sample frames: rendered scenes no shipped model "
               f"trained on.\nCoarse rotations U(0, 30) deg around the truth (seed {seed}); {models}, "
               f"{threads or 'all'} thread{'' if threads == 1 else 's'}, with K.\n")
    head = ("object", "n", "input deg", "refined deg", "ms/refinement")
    rows = []
    for obj in sorted(sessions):
        rs = [r for r in refinements if r.object_id == obj]
        rows.append((obj, str(len(rs)), f"{np.mean([r.input_error_deg for r in rs]):.1f}",
                     f"{np.mean([r.refined_error_deg for r in rs]):.1f}",
                     f"{np.median([r.ms_per_refinement for r in rs]):.2f}"))
    rows.append(("all", str(len(refinements)), f"{np.mean([r.input_error_deg for r in refinements]):.1f}",
                 f"{np.mean([r.refined_error_deg for r in refinements]):.1f}",
                 f"{np.median([r.ms_per_refinement for r in refinements]):.2f}"))
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    for r in [head, *rows]:
        click.echo("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))))
    skipped = [obj for obj in seen if obj not in sessions]
    if skipped:
        click.echo(f"\nNo shipped model for these, skipped: {', '.join(skipped)}.")
    click.echo("\nErrors: mean geodesic angle to the ground truth. Time: median of one refine() call (crop, network,\n"
               "composition) at batch 1" + ("; a cascade's call runs eight to twelve network passes." if cascade
                                            else "."))
    write_picture(out, demo.demo_picture(frames, refinements, demo.load_outlines()))
    click.echo(f"Wrote {out}: per object, ground truth (white), coarse input (cyan), refined (green).")


def _own_image(out: Path, threads: int, image_path: Path, box, q, K, object_id: str, cascade: bool = False) -> None:
    from refiner_rt import demo
    from refiner_rt import quaternion as rq
    from refiner_rt.pretrained import pretrained_models

    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if image is None:
        raise click.BadParameter(f"{image_path} is not an image OpenCV can read", param_hint="'--image'")
    shipped = sorted(m.object_id for m in pretrained_models())
    if object_id not in shipped:
        raise click.BadParameter(f"no shipped model for {object_id!r}; shipped: {', '.join(shipped) or 'none'}",
                                 param_hint="'--object'")
    h, w = image.shape[:2]
    x1, y1, x2, y2 = box
    if not (x1 < x2 and y1 < y2):
        raise click.BadParameter(f"expected x1 < x2 and y1 < y2; got {','.join(f'{v:g}' for v in box)}",
                                 param_hint="'--box'")
    if x2 <= 0 or y2 <= 0 or x1 >= w or y1 >= h:
        raise click.BadParameter(f"the box {','.join(f'{v:g}' for v in box)} lies outside the {w}x{h} image",
                                 param_hint="'--box'")
    norm = float(np.linalg.norm(q))
    if norm < 1e-6:
        raise click.BadParameter(f"expected a non-zero quaternion w,x,y,z; got {','.join(f'{v:g}' for v in q)}",
                                 param_hint="'--q'")
    q_in = rq.canonical(q / norm)
    fx, fy, cx, cy = K
    K3 = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    sess = _refiner(object_id, threads, cascade)
    try:
        sess.refine(image, box[None], q_in[None], K=K3)  # warm-up
        t0 = time.perf_counter()
        res = sess.refine(image, box[None], q_in[None], K=K3)
        ms = 1000.0 * (time.perf_counter() - t0)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    q_ref = res.q_refined[0]
    ran = ("the coarse and fine refiners" if not sess.per_call_passes else
           "one pass" + (", no fine refiner ships for it" if cascade else ""))
    click.echo(f"{object_id}: coarse q (wxyz) {np.array2string(q_in, precision=4, separator=', ')}")
    click.echo(f"{object_id}: refined q (wxyz) {np.array2string(q_ref, precision=4, separator=', ')}, "
               f"{float(rq.geodesic_angle(q_in, q_ref)):.1f} deg from the coarse one, {ms:.2f} ms ({ran})")
    outline = demo.load_outlines().get(object_id)
    write_picture(out, demo.image_picture(image, K3, box, q_in, q_ref, outline, object_id))
    click.echo(f"Wrote {out}: coarse (cyan) and refined (green) outlines, placed from the box (the refiner estimates "
               "rotation only).")
