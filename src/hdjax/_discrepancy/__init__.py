"""The discrepancy loop: greedy rounds (`loop`), the residual evidence (`evidence`), the
significance rules both data kinds share (`significance`), and the friction-only diagnosis
(`friction`).
"""
