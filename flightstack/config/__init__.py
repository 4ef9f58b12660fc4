"""Mission files: the hardened YAML loader, the schema's building blocks, the experiment and rig
schemas and the resolved mission the runtime consumes."""
