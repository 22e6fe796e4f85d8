"""rclpy glue only: message codecs, QoS profiles, stamp pairing."""
