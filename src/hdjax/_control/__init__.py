"""Controllers: the differentiable closed loop (`closed_loop`) and the loop-shaping analysis
(`loopshape`).
"""
