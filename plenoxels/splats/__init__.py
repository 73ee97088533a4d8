"""Gaussian splats of a fitted field: the splat model, its start from the grid, a differentiable rasterizer and the
distillation against the field's own renders."""
