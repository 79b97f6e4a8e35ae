"""agos.agents.vlm: policies that ask a vision-language model over an OpenAI-compatible API (AGOS-Agent and
the Baseline), their prompts, reply parsing, the HTTP client, and the offline stand-in model server."""
