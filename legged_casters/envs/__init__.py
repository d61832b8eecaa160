"""Built-in tasks; importing this package registers them."""

from legged_casters import registry
from legged_casters.envs.caster_omni import (
    CasterOmniEnv,
    caster_omni_cfg,
    caster_omni_paper_cfg,
    caster_omni_paper_train_cfg,
    caster_omni_stop_cfg,
    caster_omni_stop_train_cfg,
    caster_omni_sym_cfg,
    caster_omni_sym_train_cfg,
    caster_omni_train_cfg,
)
from legged_casters.envs.go2_flat import Go2FlatCfg, Go2FlatEnv, go2_flat_train_cfg
from legged_casters.envs.go2_wheel_flat import Go2WheelFlatCfg, Go2WheelFlatEnv, go2_wheel_flat_train_cfg

registry.register("go2_flat", Go2FlatEnv, Go2FlatCfg(), go2_flat_train_cfg())
registry.register("caster_omni", CasterOmniEnv, caster_omni_cfg(), caster_omni_train_cfg())
registry.register("caster_omni_sym", CasterOmniEnv, caster_omni_sym_cfg(), caster_omni_sym_train_cfg())
registry.register("caster_omni_stop", CasterOmniEnv, caster_omni_stop_cfg(), caster_omni_stop_train_cfg())
registry.register("caster_omni_paper", CasterOmniEnv, caster_omni_paper_cfg(), caster_omni_paper_train_cfg())
registry.register("go2_wheel_flat", Go2WheelFlatEnv, Go2WheelFlatCfg(), go2_wheel_flat_train_cfg())
