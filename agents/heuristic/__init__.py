"""agos.agents.heuristic: scripted policies from OpenCV colour and size matching (no ground truth)."""
