"""The photos, videos and masks a user hands over, and synthetic captures made for the demo, tests and bench."""
