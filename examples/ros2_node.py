"""An example ROS 2 node (needs a ROS 2 install with rclpy, message_filters and vision_msgs): refines the poses of a
detector's Detection2DArray and publishes one PoseStamped per object, with the same call `refiner-rt track --bag`
runs (refiner_rt.ros.RosRefiner.process). Topic names are examples; remap them."""
import message_filters
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from vision_msgs.msg import Detection2DArray

from refiner_rt.ros import RosRefiner
from refiner_rt.rosbag import pose_topic


class Refiner(Node):
    def __init__(self):
        super().__init__("refiner_rt")
        self.refiner, self.pubs = RosRefiner(mode="track", cascade=True), {}
        subs = [message_filters.Subscriber(self, t, n) for t, n in ((Image, "image_raw"), (CameraInfo, "camera_info"),
                                                                     (Detection2DArray, "detections"))]
        # stamps within 20 ms, as refiner-rt track --bag matches them (--sync-tolerance-ms)
        message_filters.ApproximateTimeSynchronizer(subs, 10, slop=0.02).registerCallback(self.on_frame)

    def on_frame(self, image, info, detections):
        for p in self.refiner.process(image, info, detections):
            msg = PoseStamped(header=image.header)
            position = p.position if p.position is not None else (0.0, 0.0, 0.0)  # the detection's: rotation only
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in position)
            (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
             msg.pose.orientation.w) = (float(v) for v in p.q_xyzw)
            if p.object_id not in self.pubs:
                self.pubs[p.object_id] = self.create_publisher(PoseStamped, pose_topic(p.object_id), 10)
            self.pubs[p.object_id].publish(msg)


if __name__ == "__main__":
    rclpy.init()
    rclpy.spin(Refiner())
