"""refiner_rt.draw.annotate_poses: outlines at the refined and input rotations, a legend, labels that do not overlap."""

import numpy as np

from refiner_rt import draw
from refiner_rt import quaternion as rq
from refiner_rt.demo import load_outlines, load_samples


def _colour_pixels(image, colour, tol=40):
    return np.all(np.abs(image.astype(int) - np.array(colour)) <= tol, axis=2)


def test_the_outline_is_drawn_where_the_object_is_and_turns_with_the_rotation():
    frame = load_samples()[0]
    obj = frame.objects[0]
    outlines = load_outlines()
    image = np.zeros((480, 640, 3), np.uint8)
    drawn = draw.annotate_poses(image, frame.K, [draw.PoseOverlay(obj.object_id, obj.box_xyxy, obj.q_gt)], outlines)
    green = _colour_pixels(drawn, draw.POSE_COLOURS["refined"])
    x1, y1, x2, y2 = obj.box_xyxy
    ys, xs = np.nonzero(green[40:])  # below the legend
    ys = ys + 40
    inside = (xs >= x1 - 10) & (xs <= x2 + 10) & (ys >= y1 - 10) & (ys <= y2 + 10)
    assert green[40:].sum() > 50 and inside.mean() > 0.95  # the outline hugs the box the detector drew
    turned = draw.annotate_poses(image, frame.K, [draw.PoseOverlay(
        obj.object_id, obj.box_xyxy, rq.multiply(obj.q_gt, rq.from_axis_angle([0, 1, 0], 40.0)))], outlines)
    # a 40-degree error is visible: the outlines differ on many pixels
    assert (green ^ _colour_pixels(turned, draw.POSE_COLOURS["refined"])).sum() > 100


def test_the_legend_names_the_colours_drawn_and_the_input_is_drawn_beside_the_refined_pose():
    frame = load_samples()[0]
    obj = frame.objects[0]
    image = np.zeros((480, 640, 3), np.uint8)
    q_in = rq.multiply(obj.q_gt, rq.from_axis_angle([1, 0, 0], 25.0))
    drawn = draw.annotate_poses(image, frame.K, [draw.PoseOverlay(obj.object_id, obj.box_xyxy, obj.q_gt, q_input=q_in,
                                                                  lost=True, score=0.42)], load_outlines())
    for colour in (draw.POSE_COLOURS["coarse"], draw.LOST_COLOUR):
        assert _colour_pixels(drawn[:60, :160], colour).sum() > 10  # in the legend
        assert _colour_pixels(drawn[60:], colour).sum() > 50  # and on the object
    assert draw.PoseOverlay(obj.object_id, obj.box_xyxy, obj.q_gt, lost=True, score=0.42).label == \
        f"{obj.object_id} 0.42 LOST"


def test_labels_of_objects_with_overlapping_boxes_do_not_overlap():
    placed = [(0, 0, 120, 40)]
    boxes = [(100, 100, 200, 200), (102, 101, 198, 205), (105, 98, 210, 190), (0, 0, 50, 50)]
    for box in boxes:
        rect = draw._free_spot(box, 110, 14, placed, (480, 640))
        assert not any(rect[0] < r[2] and r[0] < rect[2] and rect[1] < r[3] and r[1] < rect[3] for r in placed)
        assert 0 <= rect[0] and rect[2] <= 640 and 0 <= rect[1] and rect[3] <= 480
        placed.append(rect)


def test_an_object_without_outline_points_gets_axes():
    image = np.zeros((100, 100, 3), np.uint8)
    drawn = draw.annotate_poses(image, np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]),
                                [draw.PoseOverlay("own_object", np.array([30.0, 50, 90, 95]), rq.identity())], {})
    assert _colour_pixels(drawn[45:], draw.POSE_COLOURS["refined"]).sum() > 20


def test_an_object_placed_from_its_box_lands_where_its_true_pose_puts_it():
    """Without a translation an overlay is placed by the estimator's fit on the object's shipped extent points
    (refiner_rt.placement.fit_translation, draw.placement_points): at the true rotation, the centroid of each object
    of the sample frames (rendered, visible boxes, some occluded or cut by the border) projects within a pixel or two
    of where its true translation puts it."""
    from refiner_rt.placement import fit_translation

    outlines, errors = load_outlines(), []
    for frame in load_samples():
        shape = frame.image().shape[:2]
        for obj in frame.objects:
            outline = outlines[obj.object_id]
            R = rq.to_matrix(obj.q_gt)
            t = fit_translation(R, draw.placement_points(obj.object_id, outline), obj.box_xyxy, frame.K, shape)
            placed, true = (draw.project(outline.centroid_m[None], R, tt, frame.K)[0][0] for tt in (t, obj.t_m))
            errors.append(np.linalg.norm(placed - true))
    assert len(errors) > 20 and np.median(errors) < 1.0 and np.mean(errors) < 2.0, errors
