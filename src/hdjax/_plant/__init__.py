"""The plant: its vector field, inputs and `simulate` (`simulate`), the Rosenbrock solvers
(`rosenbrock`), the fixed-cost velocity-implicit stepper (`stepper`), and the experiment axis
over devices (`sharding`).
"""
