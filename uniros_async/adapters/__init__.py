"""Adapters to robot middleware outside uniros_async, so envs can drive arms whose drivers run there.

``uniros_async.adapters.ros1``: a pure-asyncio ROS 1 client (master and slave XML-RPC APIs, TCPROS) for arm drivers
that are ROS 1 nodes (Interbotix rx200, Niryo Ned2, ros_control), with no rospy in our process.
"""
