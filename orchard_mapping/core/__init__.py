"""Pure algorithm core: numpy, scipy, opencv, open3d, gtsam, onnxruntime. Never rclpy, never rosbags."""
