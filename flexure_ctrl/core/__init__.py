"""
Pure numeric and protocol core of flexure_ctrl.

Nothing under this package imports rclpy: it is plain numpy/scipy code that the
ROS nodes, the simulator and the command-line tools all call.
"""
