"""Tasks: the robot and what it is asked to do. Task files (spec), their observation and
reward (features) and kinematics; the env of any task a sim hosts (envs: the pusher-reach
MuJoCo env, or a task's own MuJoCo model in mujoco_task) and its scripted expert; pusher-reach's
expert and corrector, its Gymnasium wrapper and renderer."""
