"""Live topics as a data source: the trainer node over DDS, its learner, the bring-up of sim+policy pairs."""
