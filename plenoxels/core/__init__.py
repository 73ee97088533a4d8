"""The model: the grid, its rendering, optimiser and regularisers, the scene model around it and the fit."""
