"""AGOS-Dataset on the agent side: what an expert run's agents write for the dataset (Stage 3 images,
the expert's actions and messages, and fine-tuning examples with AGOS-Agent's prompts).

``writer.py`` wraps the expert policy and writes each decision to disk; ``example.py`` turns one
decision into a chat example a VLM fine-tuning tool reads. ``agos dataset build`` (deploy/dataset/build.py)
starts the agents with ``--dataset-out`` and assembles the episodes; docs/DATASET.md has the formats.
"""
