"""Image-per-node voting: ratio test over one descriptor index, epipolar RANSAC inliers (Ramisa et al. 2008)."""

from topoloc.voting.votes import DescriptorIndex, build_index, image_votes, ratio_matches

__all__ = ["DescriptorIndex", "build_index", "image_votes", "ratio_matches"]
