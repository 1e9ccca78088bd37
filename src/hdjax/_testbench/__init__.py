"""Virtual test benches: the independent numpy bench that shares no code with the plant
(`independent`), and the plant-made rig for tests that need the model exact (`rig`).
"""
