"""The model: the paper's parameters and eq. 9 (`paper`), the effects beyond it, one Module per
term (`effects`), the smooth stand-ins of sign() and u() (`smooth`), and the friction-only model
along a measured record (`friction_only`).
"""
