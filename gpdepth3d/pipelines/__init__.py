"""What a user runs end to end: sequences mapped from SfM or SLAM output (`sfm`)."""
