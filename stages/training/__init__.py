"""The training photos as the fit reads them: rays and colours, and the held-out views it checks against."""
