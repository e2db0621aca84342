"""Protocol logic as plain classes: lockstep pacing, odometry/state pairing, episode assembly from records."""
