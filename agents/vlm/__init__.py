"""VLM-backed policies: reply parsing and validation (the client and prompts come next)."""
