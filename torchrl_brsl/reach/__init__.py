"""Data-driven reachability analysis of black-box systems."""
from torchrl_brsl.reach.body_frame import BodyFrame
from torchrl_brsl.reach.cells import (NEAR_LEAVES, Cells, LeafLayout, fit_cells, held_out_factors, input_relevance,
                                      leaf_bounds, leaf_distance, leaf_gaps, leaf_layout, point_bounds,
                                      select_inputs, split_directions, tree_nodes)
from torchrl_brsl.reach.data_driven import METHODS, DataDrivenReach
from torchrl_brsl.reach.evaluation import (SampledReach, env_sample_reach, env_trajectories, noiseless_transitions,
                                          points_outside, sample_reach, worst_noise_outside)
from torchrl_brsl.reach.examples import (BlackBoxSystem, CappedVelocityServo, DoubleIntegrator, KinematicBicycle,
                                        SaturatedThrustPoint, Unicycle)
from torchrl_brsl.reach.hinges import (Features, feature_values, fit_features, fit_hinges, hinge_features,
                                      product_features, product_relaxation, prune_hinges, refine_hinges,
                                      relu_relaxation)
from torchrl_brsl.reach.lipschitz import covering_radius, residual_lipschitz
from torchrl_brsl.reach.local_step import stack_steps
from torchrl_brsl.reach.offline import collect_offline_data, load_offline_data, save_offline_data

__all__ = ["METHODS", "NEAR_LEAVES", "BlackBoxSystem", "BodyFrame", "CappedVelocityServo", "Cells", "DataDrivenReach",
           "DoubleIntegrator", "Features", "KinematicBicycle", "LeafLayout", "SampledReach", "SaturatedThrustPoint",
           "Unicycle", "collect_offline_data", "covering_radius", "env_sample_reach", "env_trajectories",
           "feature_values", "fit_cells", "fit_features", "fit_hinges", "held_out_factors", "hinge_features",
           "input_relevance", "leaf_bounds", "leaf_distance", "leaf_gaps", "leaf_layout", "load_offline_data",
           "noiseless_transitions", "point_bounds",
           "points_outside", "product_features", "product_relaxation", "prune_hinges", "refine_hinges",
           "relu_relaxation", "residual_lipschitz", "sample_reach", "save_offline_data", "select_inputs",
           "split_directions", "stack_steps", "tree_nodes", "worst_noise_outside"]
