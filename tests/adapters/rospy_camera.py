"""A real rospy camera driver stand-in; run by the system Python (``ros1_python()``), never imported.

python3 rospy_camera.py TOPIC
    publishes at 20 Hz sensor_msgs/Image (rgb8, 64x48, rows padded to a step of 200 bytes) on TOPIC and
    sensor_msgs/CompressedImage (PNG) on TOPIC/compressed, as usb_cam with image_transport does. Frame k carries
    stamp secs=1, nsecs=k and the pixels of tests/ros2/rclpy_camera.py's pattern(k). Prints ``ready``.
"""

import struct
import sys
import zlib

import rospy
from sensor_msgs.msg import CompressedImage, Image

W, H, STEP = 64, 48, 200


def pattern(k):
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
    rospy.init_node("uniros_test_camera", anonymous=True, disable_rosout=True)
    raw_pub = rospy.Publisher(topic, Image, queue_size=2)
    comp_pub = rospy.Publisher(topic + "/compressed", CompressedImage, queue_size=2)
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    rate = rospy.Rate(20)
    k = 0
    while not rospy.is_shutdown():
        k += 1
        rgb = pattern(k)
        padded = b"".join(rgb[y * W * 3 : (y + 1) * W * 3] + bytes(STEP - W * 3) for y in range(H))
        img = Image(height=H, width=W, encoding="rgb8", step=STEP, data=padded)
        img.header.stamp = rospy.Time(1, k)
        img.header.frame_id = "usb_cam"
        raw_pub.publish(img)
        comp = CompressedImage(format="png", data=png(rgb))
        comp.header = img.header
        comp_pub.publish(comp)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    main()
