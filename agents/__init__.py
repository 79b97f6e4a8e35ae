"""agos.agents: the policy side. The policy contract (``contract``), the registry of policies by
name (``registry``), the agent service process that serves one role over the bus, and the
policies: heuristic, oracle, random, fixed-latency stand-ins, and VLM agents (``vlm``).
Imports ``agos.runtime`` only.
"""
