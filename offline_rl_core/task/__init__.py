"""Tasks: the robot and what it is asked to do. The pusher-reach MuJoCo env, its scripted
expert and corrector, its Gymnasium wrapper and renderer."""
