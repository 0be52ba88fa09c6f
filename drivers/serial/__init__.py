"""Serial DNC drip-feed: link, result/request lines, configuration schema."""
