"""Bag of binary words of loop detection (paper: "Single-Side Reconstruction"): a vocabulary tree of ORB
descriptors (hierarchical k-majority), tf-idf weighted, L2-normalised keyframe vectors and their score matrix
V V^T."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse

from orchard_mapping.core.keyframe_features import DESCRIPTOR_BYTES

# ---------------------------------------------------------------------------------------------------------------------
# Bag of binary words
# ---------------------------------------------------------------------------------------------------------------------


def _hamming(des: np.ndarray, words: np.ndarray) -> np.ndarray:
    """Hamming distances (..., ) between (..., 32) uint8 descriptor arrays that broadcast against each other."""
    x = np.bitwise_xor(np.ascontiguousarray(des).view(np.uint64), np.ascontiguousarray(words).view(np.uint64))
    return np.bitwise_count(x).sum(axis=-1, dtype=np.int32)


def _k_majority(des: np.ndarray, k: int, rng: np.random.Generator, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """k-majority clustering of (M, 32) uint8 (k-means in Hamming space, bitwise majority centres).

    Seeds with k-means++. Returns centres (k', 32) uint8 with k' <= k (empty
    clusters dropped) and labels (M,) into them.
    """
    m = len(des)
    centres = [des[rng.integers(m)]]
    d_min = _hamming(des, centres[0][None]).astype(np.float64)  # (M,)
    for _ in range(1, k):
        w = d_min**2
        if w.sum() <= 0:
            break  # fewer distinct descriptors than k
        centres.append(des[rng.choice(m, p=w / w.sum())])
        d_min = np.minimum(d_min, _hamming(des, centres[-1][None]))
    C = np.array(centres)  # (k, 32)
    bits = np.unpackbits(des, axis=1)  # (M, 256) uint8
    label = np.full(m, -1)
    for _ in range(iterations):
        new = np.argmin(_hamming(des[:, None, :], C[None]), axis=1)  # (M,)
        if np.array_equal(new, label):
            break
        label = new
        order = np.argsort(label, kind="stable")
        counts = np.bincount(label, minlength=len(C))  # (k,)
        used = np.flatnonzero(counts)
        starts = np.searchsorted(label[order], used)
        sums = np.add.reduceat(bits[order], starts, axis=0, dtype=np.int32)  # (k', 256)
        C = np.packbits(2 * sums > counts[used, None], axis=1)
    return C, np.argmin(_hamming(des[:, None, :], C[None]), axis=1)


@dataclass(frozen=True)
class BinaryVocabulary:
    """A vocabulary tree of binary words (DBoW2-style hierarchical k-majority over ORB descriptors).

    Node 0 is the root; the leaves are the words. Quantising a descriptor costs
    branching * depth Hamming distances (a flat vocabulary of as many words
    would cost branching ** depth).
    """

    centres: np.ndarray  # (M, 32) uint8 node centres (row 0, the root, unused)
    children: np.ndarray  # (M, branching) int64 child nodes, -1 = none
    word_of: np.ndarray  # (M,) int64 word id of a leaf node, -1 for inner nodes

    def __len__(self) -> int:
        return int(np.count_nonzero(self.word_of >= 0))

    @staticmethod
    def train(descriptors: np.ndarray, *, branching: int = 10, depth: int = 4, iterations: int = 10,
              seed: int = 0) -> "BinaryVocabulary":
        """Hierarchical k-majority of (M, 32) uint8 descriptors into <= branching ** depth words.

        A node with no more descriptors than `branching` becomes a leaf. Raises
        ValueError for an empty input.
        """
        des = np.ascontiguousarray(np.asarray(descriptors, np.uint8).reshape(-1, DESCRIPTOR_BYTES))
        if len(des) == 0:
            raise ValueError("cannot train a vocabulary from zero descriptors")
        if branching < 2 or depth < 1:
            raise ValueError(f"need branching >= 2 and depth >= 1, got {branching}, {depth}")
        rng = np.random.default_rng(seed)
        centres = [np.zeros(DESCRIPTOR_BYTES, np.uint8)]
        children = [np.full(branching, -1, np.int64)]
        queue = [(0, np.arange(len(des)), 0)]  # (node, descriptor rows, level)
        while queue:
            node, rows, level = queue.pop()
            if level == depth or len(rows) <= branching:
                continue
            C, label = _k_majority(des[rows], branching, rng, iterations)
            if len(C) < 2:
                continue
            for j, c in enumerate(C):
                child = len(centres)
                centres.append(c)
                children.append(np.full(branching, -1, np.int64))
                children[node][j] = child
                queue.append((child, rows[label == j], level + 1))
        ch = np.array(children)  # (M, branching)
        leaf = np.all(ch < 0, axis=1)
        leaf[0] = len(ch) == 1  # a root without children is the single word
        word_of = np.where(leaf, np.cumsum(leaf) - 1, -1).astype(np.int64)
        return BinaryVocabulary(np.array(centres, np.uint8), ch, word_of)

    def quantize(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, 32) uint8 -> (N,) int64 word ids (descend to the nearest child at each level)."""
        des = np.ascontiguousarray(np.asarray(descriptors, np.uint8).reshape(-1, DESCRIPTOR_BYTES))
        node = np.zeros(len(des), np.int64)
        while len(des):
            ch = self.children[node]  # (N, b)
            inner = ch[:, 0] >= 0
            if not inner.any():
                break
            d = _hamming(des[:, None, :], self.centres[np.maximum(ch, 0)])  # (N, b)
            d = np.where(ch >= 0, d, np.iinfo(np.int32).max)
            best = ch[np.arange(len(des)), np.argmin(d, axis=1)]
            node = np.where(inner, best, node)
        return self.word_of[node]

    def histogram(self, descriptors: np.ndarray) -> np.ndarray:
        """(W,) float64 term frequencies (counts / N) of a keyframe's descriptors; zeros when N = 0."""
        words = self.quantize(descriptors)
        h = np.bincount(words, minlength=len(self)).astype(np.float64)
        return h / max(len(words), 1)

    def save(self, path: str | Path) -> None:
        """Write the vocabulary as a .npz file."""
        np.savez_compressed(path, centres=self.centres, children=self.children, word_of=self.word_of)

    @staticmethod
    def load(path: str | Path) -> "BinaryVocabulary":
        """Read a vocabulary written by `save`."""
        with np.load(path) as f:
            return BinaryVocabulary(f["centres"], f["children"], f["word_of"])


def bow_vectors(tf: np.ndarray | sparse.spmatrix, idf: np.ndarray | None = None) -> np.ndarray | sparse.csr_matrix:
    """tf (K, W) term frequencies -> (K, W) tf-idf vectors, L2-normalised (zero rows stay zero); sparse in
    (scipy), sparse out: a keyframe holds ~300 of the 10^4 words.

    idf defaults to the smoothed inverse document frequency over these K rows,
    ln((1 + K) / (1 + df)) + 1, which stays positive for a two-keyframe database.
    """
    dense = not sparse.issparse(tf)
    m = sparse.csr_matrix(np.atleast_2d(np.asarray(tf, np.float64)) if dense else tf, dtype=np.float64)
    if idf is None:
        df = np.bincount(m.indices[m.data > 0], minlength=m.shape[1])  # (W,) keyframes with each word
        idf = np.log((1.0 + m.shape[0]) / (1.0 + df)) + 1.0
    v = m @ sparse.diags(np.asarray(idf, np.float64))
    norm = np.sqrt(np.asarray(v.multiply(v).sum(axis=1)).ravel())  # (K,)
    inv = np.divide(1.0, norm, out=np.zeros_like(norm), where=norm > 0)
    out = sparse.csr_matrix(sparse.diags(inv) @ v)
    return out.toarray() if dense else out


def score_matrix(vectors: np.ndarray) -> np.ndarray:
    """(K, W) normalised BoW vectors -> (K, K) dot-product scores in [0, 1] (the paper's score matrix)."""
    return vectors @ vectors.T
