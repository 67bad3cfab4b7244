"""The families of generated scenes, one module per family (DCT Table II, curtain, heavy and
fragile objects, BEACON, people); hil_sim.world.scene_generators registers them and checks every
draw. Each family is make(name, rng) -> (draft, requirements) on a SceneDraft (draft.py)."""
