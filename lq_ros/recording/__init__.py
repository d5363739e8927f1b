"""Episode bags: the crash-safe rosbag2 MCAP writer, its metadata and reindexing, and the streaming reader."""
