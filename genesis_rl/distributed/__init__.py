"""Scale-out: Ray sessions (``ray_cluster``) and one CARLA server per parallel worker (``servers``). The
executors that use them live with what they run: ``evaluation.executors`` for campaigns."""
