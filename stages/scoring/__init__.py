"""Scores and views of a fitted scene: metrics, LPIPS, camera paths, renders from chosen cameras (evaluate)."""
