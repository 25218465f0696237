"""The methods the `rays` method is measured against: the reference paper's (`paper`) and
point-to-plane ICP against a board model (`icp`)."""
