"""A real rclpy (Jazzy, the rclpy venv) camera driver stand-in; never imported by our interpreter.

python rclpy_camera.py TOPIC
    publishes at 20 Hz, as a camera driver with image_transport does: sensor_msgs/msg/Image (rgb8, 64x48, rows
    padded to a step of 200 bytes) on TOPIC and sensor_msgs/msg/CompressedImage (PNG) on TOPIC/compressed.
    Frame k carries stamp sec=1, nanosec=k and pixels pattern(k) (below). Prints ``ready``.
"""

import struct
import sys
import zlib

import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image

W, H, STEP = 64, 48, 200


def pattern(k):
    """Row-major rgb8 bytes of frame k: r = x*4 + k, g = y*5, b = (x + y + 3*k) mod 256."""
    out = bytearray()
    for y in range(H):
        for x in range(W):
            out += bytes(((x * 4 + k) % 256, (y * 5) % 256, (x + y + 3 * k) % 256))
    return bytes(out)


def png(rgb):
    def chunk(tag, body):
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF)

    raw = b"".join(b"\x00" + rgb[y * W * 3 : (y + 1) * W * 3] for y in range(H))
    ihdr = struct.pack(">IIBBBBB", W, H, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def main():
    topic = sys.argv[1]
    rclpy.init()
    node = rclpy.create_node("uniros_test_camera")
    raw_pub = node.create_publisher(Image, topic, qos_profile_sensor_data)
    jpeg_pub = node.create_publisher(CompressedImage, topic + "/compressed", qos_profile_sensor_data)
    k = [0]

    def tick():
        k[0] += 1
        rgb = pattern(k[0])
        padded = b"".join(rgb[y * W * 3 : (y + 1) * W * 3] + bytes(STEP - W * 3) for y in range(H))
        img = Image(height=H, width=W, encoding="rgb8", step=STEP, data=padded)
        img.header.stamp.sec, img.header.stamp.nanosec, img.header.frame_id = 1, k[0], "camera_color_optical_frame"
        raw_pub.publish(img)
        comp = CompressedImage(format="rgb8; png compressed ", data=png(rgb))
        comp.header = img.header
        jpeg_pub.publish(comp)

    node.create_timer(0.05, tick)
    print("ready", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


if __name__ == "__main__":
    main()
