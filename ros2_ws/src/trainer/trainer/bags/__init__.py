"""Recorded topics as a data source: rosbag2 bags read, written, recorded and trained on in rounds."""
