"""The scene's frame: z up, the foreground box, the scene type, near/far and the held-out split (normalize)."""
