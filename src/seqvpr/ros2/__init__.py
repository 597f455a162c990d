"""seqvpr as a ROS 2 participant over DDS, with no ROS install: message types declared from the ``rosbags`` type
store (``messages``), cyclonedds participants with ROS 2's names and QoS (``dds``), the live localiser node
(``node``, ``frames``) and a bag player (``play``). Needs the ``ros2`` extra (cyclonedds)."""
