"""jax.grad through the sampled torque loop: the gradient of a step-tracking cost with respect to
the PI gains of a torque controller on the HD1 drive (locked output), checked against central
differences. Run: python experiments/tune_example.py"""

import jax

jax.config.update("jax_enable_x64", True)

from hdjax import Plant, TorqueController, TorqueGains, closed_loop, step_reference, tracking_cost
from hdjax.rig import station_hd1

st = station_hd1()
plant = Plant(st.truth, st.drive)
controller = TorqueController(friction=st.truth, drive=st.drive, sample_period=1e-3, current_limit=6.0)
reference = step_reference(15.0, duration=0.2)  # 15 N·m step, output locked


def cost(kp, ki):
    # the exact plant (fixed-step velocity-implicit steps, 2 per sample; solver="rodas3" for the smoothed one)
    traj = closed_loop(TorqueGains(kp=kp, ki=ki), plant, reference, controller=controller, substeps=2)
    return tracking_cost(traj, scale=15.0)


kp, ki = 0.2, 100.0
value, (d_kp, d_ki) = jax.jit(jax.value_and_grad(cost, argnums=(0, 1)))(kp, ki)
f = jax.jit(cost)
fd_kp = (f(kp * (1 + 1e-5), ki) - f(kp * (1 - 1e-5), ki)) / (2e-5 * kp)
fd_ki = (f(kp, ki * (1 + 1e-5)) - f(kp, ki * (1 - 1e-5))) / (2e-5 * ki)
print(f"cost {float(value):.6g}")
print(f"d cost/d kp: AD {float(d_kp):.6g}, central differences {float(fd_kp):.6g}")
print(f"d cost/d ki: AD {float(d_ki):.6g}, central differences {float(fd_ki):.6g}")
