"""Picks: grasps on the part (grasps), the gripper as primitives (gripper), and a collision-free,
ranked pick per posed part (plan)."""
