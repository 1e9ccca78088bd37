"""Data: datasets read and checked (`load`), experiments as batched Modules (`experiment`),
datasets written (`write`).
"""
