"""ROS 2 topics over DDS without ROS: message types (messages), conversion and validation (convert), and the receiver thread that feeds a SensorInbox (receiver)."""
