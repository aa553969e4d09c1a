"""``ponytail_ros.bench.scale_out``'s layouts: every character in exactly one node. (The figures
themselves are a benchmark's: ``python -m ponytail_ros.bench.scale_out`` prints them.)"""
import pytest

from ponytail_ros.bench.scale_out import split


@pytest.mark.parametrize('characters,nodes', [(100, 2), (101, 2), (7, 3), (5, 5), (1, 1)])
def test_split_keeps_every_character_and_balances_within_one(characters, nodes):
    groups = split(characters, nodes)
    assert len(groups) == nodes and sum(groups) == characters
    assert max(groups) - min(groups) <= 1 and min(groups) >= 1


@pytest.mark.parametrize('characters,nodes', [(3, 4), (3, 0)])
def test_split_refuses_empty_or_missing_nodes_naming_nodes(characters, nodes):
    with pytest.raises(ValueError, match='^nodes = '):
        split(characters, nodes)
