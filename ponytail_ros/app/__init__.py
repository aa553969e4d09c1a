"""The application layer: what the ponytail node does, without rclpy.

Between the ROS-free core (``ponytail_ros.core``: scene, simulator) and its two front ends, the
live node (``ponytail_ros.ros``) and the offline tools (``ponytail_ros.recording``): the runner
that turns timestamped poses into ticks (``runner.py``), the parameter table and scene building
(``parameters.py``, ``param_values.py``), the node's behaviour as messages (``node_core.py``,
``messages.py``), the one output interface of a tick (``sink.py``) and the scripted head
(``head_script.py``). It imports no rclpy (``test_layers.py`` checks): the message classes it
builds are plain rosidl Python types.
"""
