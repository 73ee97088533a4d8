"""The fit stage's wing: the training photos as the fit reads them (rays and colours, and the held-out views it checks
against), and the record and summary a fit writes of itself."""
